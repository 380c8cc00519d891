"""What a life split leaves to know: the tracker fed the true damage instead of the pipeline's estimates.

A life split's prognostic figures (the prognostic horizon, the end of life flagged within one inspection) are
bounded by more than the FDI: the wear process itself is random (eps redrawn every few hundred hours, the
actuator's own rate scale s to be learnt from the damage's growth), and the RUL's end of life is where the
pipeline's health classifier, a surrogate of phi_a, turns faulty, while the truth's is where phi_a does (which
along a damage path is not even monotone: it can turn healthy again). Feeding the same tracker the true k plus
a small Gaussian error ``error_std`` removes the FDI from the chain and measures that bound on the same
histories (``scripts/tracking_limit.py``; docs/prognostics.md, "What the histories leave to know"):

* ``tracking``: the tracker's figures with (almost) perfect measurements, scored by
  :func:`~phm_torch.prognostics.life_metrics.evaluate_life` as a phm-track run is;
* ``classifier_on_true_k``: where the health classifier applied to the true k of each inspection flags the
  end of life (no filter, no FDI): the best any RUL built on that classifier can flag it.

A target the limit misses on a split is one no FDI can reach there with this classifier and damage law.
With ``readings`` (:func:`fused_readings` of a phm-track run) and ``components``, those components are read as the
run fused them instead (the other ones exact): which component's measurement costs the horizon.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any

import torch

from ..faults import FAULT_NAMES, N_FAULTS
from ..online.diagnosis import censor
from ..prognostics.life_metrics import evaluate_life
from .fleet import tracker_healthy
from .measurement import READINGS, interval_scale
from .particle_filter import Tracker
from .particle_rul import ParticleRUL


def _truth_actuators(truth: Mapping[str, Any]) -> dict[str, list[Mapping[str, Any]]]:
    """{actuator: inspections} of a truth.json, each inspection with 8 finite ``k_true``; else ValueError."""
    actuators = truth.get("actuators")
    if not isinstance(actuators, Mapping) or not actuators:
        raise ValueError("truth: needs a non-empty 'actuators' mapping (a life split's truth.json)")
    out = {}
    for a, history in actuators.items():
        inspections = history.get("inspections") or []
        for j, row in enumerate(inspections):
            k = row.get("k_true")
            if not isinstance(k, list) or len(k) != N_FAULTS or not all(math.isfinite(float(v)) for v in k):
                raise ValueError(
                    f"truth: actuator {a!r} inspection {j}: k_true must be {N_FAULTS} finite values, got {k!r}"
                )
        out[a] = list(inspections)
    return out


Readings = dict[str, list[tuple[torch.Tensor, torch.Tensor]]]


def fused_readings(track: Mapping[str, Any], dof: float = math.inf) -> Readings:
    """{actuator: [(k (8,), error scale (8,))]} per inspection of a phm-track ``track.json``: the reading its filter
    fused and that reading's scale (:func:`~.measurement.interval_scale` of its 90 % interval)."""
    out: Readings = {}
    for a, history in track["actuators"].items():
        rows = []
        for j, row in enumerate(history["inspections"]):
            key, interval = next(((k, i) for k, i in READINGS if row.get(k) is not None), (None, None))
            if key is None or row.get(interval) is None:
                raise ValueError(f"track: actuator {a!r} inspection {j} has no k_hat with its interval")
            k = torch.tensor([row[key][n] for n in FAULT_NAMES], dtype=torch.float64)
            lo, hi = (torch.tensor([row[interval][n][b] for n in FAULT_NAMES], dtype=torch.float64) for b in (0, 1))
            rows.append((k, interval_scale(k, lo, hi, dof)))
        out[a] = rows
    return out


def classifier_faulty(rul: ParticleRUL, k: torch.Tensor) -> torch.Tensor:
    """(B,) bool: the pipeline's health classifier calls the fault vectors k (B, 8) faulty (score <= 0)."""
    return rul.score(k.to(torch.float64)) <= 0.0


def track_truth(
    tracker: Tracker,
    truth: Mapping[str, Any],
    error_std: float = 1e-4,
    seed: int = 0,
    readings: Readings | None = None,
    components: tuple[int, ...] = (),
) -> dict[str, Any]:
    """Track every actuator of ``truth`` from its true k plus N(0, error_std^2) per component.

    Args:
        tracker: a fresh tracker with its RUL model (:func:`~.builder.build_tracker`); its settings decide as in
            phm-track (``verdict: record`` reads each inspection's own verdict, here the health classifier on the
            measured k; ``posterior``: the posterior's alone).
        truth: a life split's truth.json (``actuators`` -> ``inspections`` with ``hours`` and ``k_true``).
        error_std: [k units] the measurement error, also the filter's error scale; > 0.
        seed: of the measurement errors.
        readings, components: with :func:`fused_readings` of a run on the same split, the 0-based ``components``
            are read (value and scale) as that run fused them.

    Returns a track in phm-track's layout ({"actuators": {id: {"inspections": [...]}}}, with ``error_std`` and
    ``components_as_read`` beside) with, per inspection,
    ``hours``, ``k_hat`` (the measured k), ``rul_hours`` (5/50/95 %, None where censored), ``rul_censored``,
    ``healthy``, ``out_of_distribution`` (False) and, as its snapshot, the health classifier on the true k
    (``snapshot_healthy``; no snapshot RUL).
    """
    if not (isinstance(error_std, (int, float)) and math.isfinite(error_std) and error_std > 0):
        raise ValueError(f"error_std must be a finite number > 0, got {error_std!r}")
    if tracker.rul_model is None:
        raise ValueError("track_truth: the tracker has no RUL model (build it with build_tracker)")
    if tracker.rows:
        raise ValueError("track_truth: the tracker has tracked actuators already; give it a fresh one")
    histories = _truth_actuators(truth)
    if components and readings is None:
        raise ValueError(f"components {list(components)}: needs the readings of a phm-track run (fused_readings)")
    if any(not 0 <= c < N_FAULTS for c in components):
        raise ValueError(f"components must be in [0, {N_FAULTS}), got {list(components)}")
    for a, v in histories.items():
        if components and len(readings.get(a, [])) != len(v):
            raise ValueError(f"readings: actuator {a!r} has {len(readings.get(a, []))} inspections, the truth {len(v)}")
    record_verdict = tracker.settings.verdict == "record"
    g = torch.Generator().manual_seed(int(seed))
    out: dict[str, dict[str, Any]] = {a: {"inspections": []} for a in histories}
    for j in range(max((len(v) for v in histories.values()), default=0)):
        batch = [a for a, v in histories.items() if len(v) > j]
        k_true = torch.tensor([histories[a][j]["k_true"] for a in batch], dtype=torch.float64)
        scale = torch.full_like(k_true, float(error_std))
        k_hat = (k_true + scale * torch.randn(k_true.shape, generator=g, dtype=torch.float64)).clamp(0.0, 1.0)
        if components:
            cols = torch.tensor(components)
            k_hat[:, cols] = torch.stack([readings[a][j][0] for a in batch])[:, cols]
            scale[:, cols] = torch.stack([readings[a][j][1] for a in batch])[:, cols]
        hours = torch.tensor([float(histories[a][j]["hours"]) for a in batch], dtype=torch.float64)
        if j > 0:
            previous = torch.tensor([float(histories[a][j - 1]["hours"]) for a in batch], dtype=torch.float64)
            bad = (hours <= previous).nonzero().flatten().tolist()
            if bad:
                a = batch[bad[0]]
                raise ValueError(f"truth: actuator {a!r} inspection {j}: hours {float(hours[bad[0]])} not increasing")
        measured_faulty = classifier_faulty(tracker.rul_model, k_hat)
        post = tracker.update(
            batch,
            hours,
            k_hat,
            scale,
            torch.ones(len(batch), dtype=torch.bool),
            measured_faulty & record_verdict,
        )
        true_faulty = classifier_faulty(tracker.rul_model, k_true)
        for i, a in enumerate(batch):
            rul, censored = censor(post.rul[i].tolist(), tracker.law.horizon_hours)
            reading = {"healthy": not bool(measured_faulty[i])}  # the inspection's own verdict, as phm-predict's
            out[a]["inspections"].append(
                {
                    "hours": float(hours[i]),
                    "k_hat": k_hat[i].tolist(),
                    "rul_hours": rul,
                    "rul_censored": censored,
                    "healthy": tracker_healthy(reading, rul, True, record_verdict),
                    "out_of_distribution": False,
                    "snapshot_healthy": not bool(true_faulty[i]),
                    "snapshot_rul_hours": None,
                }
            )
    return {"error_std": float(error_std), "components_as_read": [FAULT_NAMES[c] for c in components], "actuators": out}


def information_limit(track: Mapping[str, Any], truth: Mapping[str, Any]) -> dict[str, Any]:
    """The two bounds of a life split (module docstring) from :func:`track_truth`'s ``track`` of ``truth``:
    ``tracking`` (the tracker fed the true k, phm-track's fleet figures and targets) and ``classifier_on_true_k``
    (its end-of-life flags), with the track's ``error_std``, ``components_as_read`` and the count of actuators; each
    figure as :func:`~phm_torch.prognostics.life_metrics.evaluate_life` computes it."""
    scored = evaluate_life(track, truth)
    snapshot = scored["snapshot"]
    return {
        "error_std": track["error_std"],
        "components_as_read": track["components_as_read"],
        "n_actuators": scored["n_actuators"],
        "tracking": scored["tracker"],
        "targets": scored["targets"],
        "classifier_on_true_k": {
            key: snapshot[key]
            for key in (
                "eol_flagged_within_one_inspection",
                "eol_flagged_early",
                "eol_never_flagged",
                "eol_detection_delay",
            )
        },
    }
