"""A whole fleet through the tracker: index rows -> diagnoses -> filter -> ``track.json`` records, resumable.

Actuators are processed in fixed chunks (``chunk_size`` consecutive actuators of the index): the chunk's records
are diagnosed, then the filter runs one round per inspection number across the chunk's actuators (a batched
update), and each actuator's state is written atomically (:mod:`.state`). A rerun skips every chunk whose
actuators all have a state with the run's fingerprint and recomputes the others whole, with the same batches
as an uninterrupted run, so both give the same numbers.
"""

from __future__ import annotations

import logging
import os
from collections.abc import Callable, Mapping, Sequence
from typing import Any

import torch

from ..faults import FAULT_NAMES
from ..online.diagnosis import QUANTILES, censor
from .index import Inspection
from .inspection import measurement, unread
from .measurement import interval_scale, verdict_odds
from .particle_filter import Posterior, Tracker
from .state import fingerprint, load_state, save_state
from .timing_spread import read_shift

log = logging.getLogger(__name__)

Diagnose = Callable[[Sequence[Inspection]], list[dict[str, Any]]]


def tracker_healthy(
    diagnosis: Mapping[str, Any], rul: Mapping[str, float | None] | None, fused: bool, record_verdict: bool
) -> bool:
    """The tracker's verdict: faulty wherever the posterior's median RUL is 0 (most of its probability past the
    health classifier's boundary; the filter reports it 0 also where its ``faulty_at`` quantile is); with
    ``record_verdict`` also wherever a fused inspection's own (phm-predict's) verdict is faulty. Before a track, the
    record's own verdict."""
    if rul is None:
        return bool(diagnosis["healthy"])
    past = rul["p50"] is not None and rul["p50"] <= 0.0
    return (bool(diagnosis["healthy"]) or not fused or not record_verdict) and not past


def inspection_record(
    row: Inspection,
    diagnosis: Mapping[str, Any],
    post: Posterior,
    i: int,
    fused: bool,
    horizon: float,
    record_verdict: bool = False,
    k_corrected: tuple[list[float], list[float], list[float]] | None = None,
    held: list[str] | None = None,
) -> dict[str, Any]:
    """One inspection of ``track.json`` (row ``i`` of the batch summary ``post``); ``k_corrected``: (k, lower,
    upper), the reading the filter fused where a response is used, k_hat and its interval through the FDI response's
    inverse (written as ``k_hat_corrected`` and ``k_hat_corrected_interval``; the near-nominal FDI's reading, where
    it has one, as ``k_hat_near_nominal`` and ``k_hat_near_nominal_interval``); ``held``: the components of a fused
    reading the filter did not read (:func:`~.inspection.unread`), written as ``k_not_fused``."""
    tracked = bool(post.tracked[i])
    rul, rul_censored = censor(post.rul[i].tolist(), horizon) if tracked else (None, False)
    snap = diagnosis.get("rul_hours")
    snapshot, snap_censored = censor([snap[q] for q in QUANTILES], horizon) if snap is not None else (None, False)
    out = {
        "hours": row.hours,
        "file": row.file,
        "event": row.event or None,
        "k_hat": dict(diagnosis["k_hat"]),
        "k_interval": diagnosis.get("k_interval"),
        "k_filtered": dict(zip(FAULT_NAMES, post.k_mean[i].tolist())) if tracked else None,
        "k_filtered_interval": {
            n: [lo, hi] for n, lo, hi in zip(FAULT_NAMES, post.k_low[i].tolist(), post.k_high[i].tolist())
        }
        if tracked
        else None,
        "rate_scale": dict(zip(QUANTILES, post.rate_scale[i].tolist())) if tracked else None,
        "p_faulty": diagnosis.get("p_faulty"),
        "healthy": tracker_healthy(diagnosis, rul, fused, record_verdict),
        "snapshot_healthy": bool(diagnosis["healthy"]),
        "rul_hours": rul,
        "rul_censored": rul_censored,
        "out_of_distribution": bool(diagnosis["out_of_distribution"]),
        "ood_reasons": list(diagnosis.get("ood_reasons", [])),
        "fused": fused,
        "k_not_fused": list(held or []) if fused else None,
        "snapshot_rul_hours": snapshot,
        "snapshot_rul_censored": snap_censored,
        "noise": diagnosis.get("noise"),
        # the timing scan's best shift [s] (tracking/timing_spread.py: whether the fleet's records came on time)
        "timing_best_shift_s": read_shift(diagnosis),
        # what phm-predict's path corrected (a trigger offset, a reversed probe) or refused, one line each
        "messages": list(diagnosis.get("messages", [])),
    }
    if k_corrected is not None and diagnosis.get("k_near_nominal") is None:
        k, lower, upper = k_corrected
        out["k_hat_corrected"] = dict(zip(FAULT_NAMES, k))
        out["k_hat_corrected_interval"] = {n: [a, b] for n, a, b in zip(FAULT_NAMES, lower, upper)}
    if diagnosis.get("k_near_nominal") is not None:
        out["k_hat_near_nominal"] = dict(diagnosis["k_near_nominal"])
        out["k_hat_near_nominal_interval"] = dict(diagnosis["k_near_nominal_interval"])
    return out


def _run_chunk(
    tracker: Tracker, model: Any, rows: Mapping[str, list[Inspection]], diagnose: Diagnose
) -> dict[str, list[dict[str, Any]]]:
    """Diagnose and filter the inspections of a few actuators; {actuator: inspection records}."""
    flat = [row for actuator_rows in rows.values() for row in actuator_rows]
    found = diagnose(flat)
    if len(found) != len(flat):
        raise ValueError(f"diagnose returned {len(found)} diagnoses for {len(flat)} records")
    diagnoses = dict(zip(((r.actuator, r.line) for r in flat), found))
    dof = tracker.settings.measurement_dof
    out: dict[str, list[dict[str, Any]]] = {a: [] for a in rows}
    for r in range(max(len(v) for v in rows.values())):
        batch = [v[r] for v in rows.values() if len(v) > r]
        diag = [diagnoses[(row.actuator, row.line)] for row in batch]
        meas = [measurement(model, d) for d in diag]
        k_hat, lower, upper = (torch.stack([m[j] for m in meas]) for j in range(3))
        if tracker.response is not None:  # the FDI's mean response near nominal inverted (:mod:`.response`)
            corrected = tracker.response.correct(k_hat, lower, upper)
            pipeline_read = torch.tensor([d.get("k_near_nominal") is None for d in diag]).unsqueeze(1)
            k_hat, lower, upper = (torch.where(pipeline_read, c, v) for c, v in zip(corrected, (k_hat, lower, upper)))
        scale = interval_scale(k_hat, lower, upper, dof)
        held = [unread(d, tracker.not_identified) for d in diag]
        observed = torch.tensor([[n not in h for n in FAULT_NAMES] for h in held])
        observed = None if bool(observed.all()) else observed  # every component read: the plain update
        fuse = torch.tensor([not d["out_of_distribution"] for d in diag])
        record_verdict = tracker.settings.verdict == "record"
        faulty = torch.tensor([not d["healthy"] and record_verdict for d in diag])
        restart = torch.tensor([row.event == "maintenance" for row in batch])
        odds = verdict_odds([d.get("p_faulty") for d in diag], tracker.verdict_prior)
        post = tracker.update(
            [row.actuator for row in batch],
            torch.tensor([row.hours for row in batch]),
            k_hat,
            scale,
            fuse,
            faulty,
            restart,
            odds,
            observed,
        )
        for i, (row, d) in enumerate(zip(batch, diag)):
            out[row.actuator].append(
                inspection_record(
                    row,
                    d,
                    post,
                    i,
                    bool(fuse[i]) and bool(post.tracked[i]),
                    tracker.law.horizon_hours,
                    record_verdict,
                    None if tracker.response is None else (k_hat[i].tolist(), lower[i].tolist(), upper[i].tolist()),
                    held[i],
                )
            )
    return out


def track_fleet(
    index: Mapping[str, list[Inspection]],
    tracker: Tracker,
    model: Any,
    diagnose: Diagnose,
    state_dir: str | os.PathLike | None = None,
    run_key: Any = None,
    chunk_size: int = 64,
) -> dict[str, dict[str, Any]]:
    """Track every actuator of ``index`` ({actuator: inspections in time order}, :func:`~.index.read_index`).

    Args:
        tracker: the filter (its settings and law are part of the run's fingerprint via ``run_key``).
        model: the exported pipeline.
        diagnose: inspections -> their diagnoses, in order (phm-predict's, :mod:`.inspection`).
        state_dir: folder of the per-actuator states (None: not resumable).
        run_key: JSON-able description of the run (pipeline hash, settings, law): a state made under another
            key is recomputed.
        chunk_size: actuators per batched filter run.

    Returns {actuator: {"inspections": [...]}} in index order.
    """
    if chunk_size < 1:
        raise ValueError(f"chunk_size must be >= 1, got {chunk_size!r}")
    actuators = list(index)
    result: dict[str, dict[str, Any]] = {}
    resumed = 0
    for start in range(0, len(actuators), chunk_size):
        chunk = actuators[start : start + chunk_size]
        keys = {a: fingerprint([run_key, [(r.hours, r.file, r.event) for r in index[a]]]) for a in chunk}
        stored = {a: load_state(state_dir, a, keys[a]) for a in chunk} if state_dir is not None else {}
        if state_dir is not None and all(v is not None for v in stored.values()):
            for a in chunk:
                particles, inspections = stored[a]
                tracker.load_state(a, particles)
                result[a] = {"inspections": inspections}
            resumed += len(chunk)
            continue
        records = _run_chunk(tracker, model, {a: index[a] for a in chunk}, diagnose)
        for a in chunk:
            result[a] = {"inspections": records[a]}
            if state_dir is not None:
                save_state(state_dir, a, keys[a], tracker.state(a), records[a])
    if resumed:
        log.info("resumed %d of %d actuators from %s", resumed, len(actuators), state_dir)
    return result


def fleet_list(actuators: Mapping[str, dict[str, Any]]) -> list[dict[str, Any]]:
    """The latest state of each actuator, sorted by RUL 5 % (censored or unknown last, then by id)."""
    rows = []
    for a, track in actuators.items():
        if not track["inspections"]:
            continue
        last = track["inspections"][-1]
        rows.append(
            {
                "actuator": a,
                "hours": last["hours"],
                "rul_hours": last["rul_hours"],
                "rul_censored": last["rul_censored"],
                "healthy": last["healthy"],
                "p_faulty": last["p_faulty"],
            }
        )

    def key(row: dict[str, Any]) -> tuple[int, float, str]:
        p5 = (row["rul_hours"] or {}).get("p5")
        return (1, 0.0, row["actuator"]) if p5 is None else (0, p5, row["actuator"])

    return sorted(rows, key=key)
