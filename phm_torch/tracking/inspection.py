"""The pipeline's answer on each inspection record: phm-predict's diagnosis, as the tracker's measurement.

Per record (:func:`inspect_record`) the tracker takes phm-predict's own path
(:func:`~phm_torch.online.diagnosis.diagnose` with the pipeline's input contract), so an inspection's k_hat,
interval, verdict, OOD flag and reasons are exactly phm-predict's; the snapshot RUL stored beside the
tracker's is phm-predict's ``rul_hours``. :func:`inspect_currents` is the same diagnosis for current-only
records held in memory, batched through the pipeline (the fleet benchmark): a record without command and
position columns skips the same two checks in :func:`diagnose`; it leaves out diagnose's corrections of a bench's
record (its hum lines, a probe offset read at rest: the benchmark's simulated records have neither), so its figures
are those of clean records.
"""

from __future__ import annotations

import math
from typing import Any

import torch

from ..faults import FAULT_NAMES
from ..online.bench_check import BenchCheck
from ..online.corruptions import Record, delayed
from ..online.diagnosis import NOISE_FLOOR, calibrated_interval, diagnose
from ..online.input_contract import InputContract, pipeline_reasons
from ..online.probe_calibration import ProbeCalibration
from ..online.timing_tolerance import reading_shifts
from .measurement import Z95
from .near_nominal import NearNominalFDI
from .timing_spread import ALIGN_TOLERANCE_S


def require_calibrated(model: Any, source: str) -> None:
    """A pipeline whose k_hat intervals are NaN (not calibrated by phm-evaluate) cannot weigh its estimates."""
    widths = getattr(model, "k_half_widths", None)
    if widths is None or not hasattr(model, "k_interval") or not bool(torch.isfinite(widths).all()):
        raise ValueError(
            f"pipeline {source}: no calibrated k_hat intervals (k_half_widths NaN or absent), so the "
            f"tracker cannot weigh its estimates; export it with a rul_calibration.json written by "
            f"phm-evaluate"
        )


def inspect_record(
    model: Any,
    record: Record,
    contract: InputContract,
    bench_nominal: torch.Tensor | None = None,
    bench: BenchCheck | None = None,
    near_nominal: NearNominalFDI | None = None,
    probe: ProbeCalibration | None = None,
    timing_tolerance_s: float = 0.0,
    align_timing: bool = False,
) -> dict[str, Any]:
    """phm-predict's diagnosis of one record (the dict of :func:`diagnose`), moved onto the training model with the
    bench's healthy record ``bench_nominal`` (n_full,) [A] where given (phm-predict's ``baseline``). With a
    ``near_nominal`` FDI, an in-distribution record near nominal also gets ``k_near_nominal`` and its interval
    ``k_near_nominal_interval`` (:mod:`.near_nominal`), which the tracker reads instead of k_hat. With a
    ``timing_tolerance_s`` (phm-track's ``timing_tolerance``) both intervals hold every reading within it, as
    phm-predict's (:mod:`~phm_torch.online.timing_tolerance`); 0 reads the record at its own timing. With
    ``align_timing`` (phm-track's ``timing_align``) a record the timing scan reads best moved is read again moved
    back by that shift (``timing_aligned_s``), where it stays in distribution, and every record within
    ``ALIGN_TOLERANCE_S`` at least (the scan's own error near nominal)."""

    if align_timing:  # an aligned record's timing is the scan's, within its own error: read within that too
        timing_tolerance_s = max(timing_tolerance_s, ALIGN_TOLERANCE_S)

    def read(r: Record) -> dict[str, Any]:
        return diagnose(
            model,
            r,
            contract,
            bench_nominal,
            bench,
            keep_current=near_nominal is not None,
            probe=probe,
            timing_tolerance_s=timing_tolerance_s,
        )

    found = read(record)
    scan = found["timing_check"]
    if align_timing and scan is not None and not found["out_of_distribution"]:
        lag = round(scan["best_shift_s"] * float(model.sample_rate))
        if lag != 0:
            again = read(Record(record.time, record.command, record.position, delayed(record.current, -lag)))
            if not again["out_of_distribution"]:
                found = {**again, "timing_aligned_s": scan["best_shift_s"]}
    current = found.pop("current", None)
    if near_nominal is None or found["out_of_distribution"] or found["noise"] is None:
        return found
    m = model.module if hasattr(model, "module") else model
    with torch.no_grad():
        alpha, readable = near_nominal.coefficients(m, current)
    if not bool(readable[0]):  # missing samples: the pipeline's own estimate
        return found
    k_pipeline = torch.tensor([[found["k_hat"][n] for n in FAULT_NAMES]], dtype=torch.float64)
    with torch.no_grad():
        used, k, lower, upper = near_nominal.read(
            alpha, k_pipeline, torch.tensor([found["noise"]], dtype=torch.float64)
        )
    if bool(used[0]):
        if found.get("probe_offset_std") is not None:
            lower, upper = _with_offset_error(near_nominal, m, current, k_pipeline, found, k)
        found["k_near_nominal"] = dict(zip(FAULT_NAMES, k[0].tolist()))
        found["k_near_nominal_interval"] = {
            n: [a, b] for n, a, b in zip(FAULT_NAMES, lower[0].tolist(), upper[0].tolist())
        }
        found["k_near_nominal_not_identified"] = near_nominal.not_identified(found["noise"])
        if found["timing_tolerance"] is not None:
            _near_nominal_within_tolerance(near_nominal, m, float(model.sample_rate), current, k_pipeline, found)
    return found


def _near_nominal_within_tolerance(
    near_nominal: NearNominalFDI,
    model: Any,
    rate: float,
    current: torch.Tensor,
    k_pipeline: torch.Tensor,
    found: dict[str, Any],
) -> None:
    """The near-nominal reading's interval widened, in ``found``, to its readings at every shift diagnose read the
    record at (``found["timing_tolerance"]``: the tolerance, and the timing scan's best shift beyond it; ``rate``
    [Hz] the pipeline's sample rate)."""
    tolerance = found["timing_tolerance"]
    best = tolerance.get("widened_to_s")
    shifts = reading_shifts(
        current.shape[-1], rate, tolerance["tolerance_s"], None if best is None else round(best * rate)
    )
    x = current.reshape(-1).double()
    # the ends held, not missing: the network reads a record missing more than a few samples not at all
    block = torch.stack([delayed(x, -s) for s in shifts]).to(current.dtype)
    noise = torch.full((len(shifts),), float(found["noise"]), dtype=torch.float64)
    with torch.no_grad():
        alpha, readable = near_nominal.coefficients(model, block)
        used, _, lower, upper = near_nominal.read(alpha, k_pipeline.expand(len(shifts), -1), noise)
    keep = used & readable
    if not bool(keep.any()):
        return
    bounds = found["k_near_nominal_interval"]
    low, high = lower[keep].amin(0).tolist(), upper[keep].amax(0).tolist()
    found["k_near_nominal_interval"] = {
        n: [min(bounds[n][0], a), max(bounds[n][1], b)] for n, a, b in zip(FAULT_NAMES, low, high)
    }


def _with_offset_error(
    near_nominal: NearNominalFDI,
    model: Any,
    current: torch.Tensor,
    k_pipeline: torch.Tensor,
    found: dict[str, Any],
    k: torch.Tensor,
) -> tuple[torch.Tensor, torch.Tensor]:
    """The near-nominal reading k (1, 8)'s 90 % bounds (1, 8) widened by the error of the probe offset diagnose
    removed (``probe_offset_std``): that offset was read over the rest window (48 samples on the reference), so it is
    off by the window mean's noise, and a constant shift of the record moves the near-nominal readings several times
    their own error. The reading's response to +-1 std of it, in quadrature with the calibrated half-widths. Without
    this, a clean record whose noise crossed the removal's gate was fused as a precise reading 0.005-0.03 off (40
    histories at 3 % noise: coverage 86.9 -> 82.8 % from 4 such inspections)."""
    noise = torch.tensor([found["noise"]], dtype=torch.float64)
    std = float(found["probe_offset_std"])
    with torch.no_grad():
        shifted = [
            near_nominal.read(near_nominal.coefficients(model, current + sign * std)[0], k_pipeline, noise)[1]
            for sign in (1.0, -1.0)
        ]
        w = near_nominal.half_widths(noise).to(torch.float64)
    half = (w.pow(2) + (Z95 * (shifted[0] - shifted[1]).abs() / 2.0).pow(2)).sqrt()
    return (k - half).clamp(0.0, 1.0), (k + half).clamp(0.0, 1.0)


def inspect_currents(
    model: Any, currents: torch.Tensor, contract: InputContract, near_nominal: NearNominalFDI | None = None
) -> list[dict[str, Any]]:
    """The diagnoses of current-only records (B, n_full) [A], batched: the fields of :func:`diagnose` that the
    tracker reads (k_hat, k_interval, healthy, p_faulty, rul_hours, out_of_distribution, ood_reasons, noise; with a
    ``near_nominal`` FDI, its reading where gated, as :func:`inspect_record`)."""
    x = currents.to(model.times.dtype)
    with torch.no_grad():
        noise = model.noise_level(x)
        k_hat, score, rul, ood, _ = model(x)
        lower, upper = model.k_interval(k_hat, noise.to(k_hat.dtype))
        p_faulty = model.faulty_probability(score)
        near = None
        if near_nominal is not None:
            alpha, readable = near_nominal.coefficients(model, x)
            used, k_near, lo_near, hi_near = near_nominal.read(alpha, k_hat, noise)
            used = used & readable
            near = (used.tolist(), k_near.tolist(), lo_near.tolist(), hi_near.tolist())
    flagged = ood.nonzero().flatten().tolist()
    found = pipeline_reasons(model, x[flagged]) if flagged else []
    own = dict(zip(flagged, found or [[] for _ in flagged]))
    # the batch's numbers as Python lists once (per-record tensor indexing and tolist cost more than the pipeline)
    k_list, lo_list, hi_list = k_hat.tolist(), lower.tolist(), upper.tolist()
    score_list, rul_list, p_list, noise_list = score.tolist(), rul.tolist(), p_faulty.tolist(), noise.tolist()
    noise_max = max(2.0 * float(model.calibration_noise), NOISE_FLOOR)
    out = []
    for i in range(x.shape[0]):
        reasons = (own[i] or ["pipeline"]) if i in own else []
        reasons += [r for r in contract.current_reasons(model, x[i], noise_list[i], k_hat[i]) if r not in reasons]
        bad = bool(reasons)
        r = rul_list[i]
        out.append(
            {
                "k_hat": dict(zip(FAULT_NAMES, k_list[i])),
                "k_interval": None if bad else {n: [a, b] for n, a, b in zip(FAULT_NAMES, lo_list[i], hi_list[i])},
                "health_score": score_list[i],
                "healthy": score_list[i] > 0,
                "p_faulty": None if bad or math.isnan(p_list[i]) else p_list[i],
                "rul_hours": None if bad or any(math.isnan(v) for v in r) else dict(zip(("p5", "p50", "p95"), r)),
                "out_of_distribution": bad,
                "ood_reasons": reasons,
                "checks_skipped": ["command", "tracking"],
                "noise": noise_list[i],
                "noise_above_calibration": noise_list[i] > noise_max,
            }
        )
        if near is not None and near[0][i] and not bad:
            out[-1]["k_near_nominal"] = dict(zip(FAULT_NAMES, near[1][i]))
            out[-1]["k_near_nominal_interval"] = {n: [a, b] for n, a, b in zip(FAULT_NAMES, near[2][i], near[3][i])}
            out[-1]["k_near_nominal_not_identified"] = near_nominal.not_identified(noise_list[i])
    return out


def unread(diagnosis: dict[str, Any], pipeline_unread: list[str]) -> list[str]:
    """The components of one diagnosis's reading (:func:`measurement`) that measure nothing (their estimate is the
    training prior): the near-nominal FDI's own (R^2 on its held-out records at the record's noise) where it reads
    the record and carries them, else ``pipeline_unread`` (the pipeline's, from phm-evaluate's ``identifiability``:
    :func:`~phm_torch.online.diagnosis.not_identified`)."""
    own = diagnosis.get("k_near_nominal_not_identified") if diagnosis.get("k_near_nominal") is not None else None
    return list(own) if own is not None else list(pipeline_unread)


def measurement(model: Any, diagnosis: dict[str, Any]) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """(k_hat (8,), lower (8,), upper (8,)) of one diagnosis: the near-nominal FDI's reading where it has one, else
    the pipeline's. Out of distribution, phm-predict reports no interval: the calibrated one is recomputed (only
    for the record; an OOD inspection is never fused)."""
    if diagnosis.get("k_near_nominal") is not None:
        bounds = torch.tensor([diagnosis["k_near_nominal_interval"][n] for n in FAULT_NAMES], dtype=torch.float64)
        k = torch.tensor([diagnosis["k_near_nominal"][n] for n in FAULT_NAMES], dtype=torch.float64)
        return k, bounds[:, 0], bounds[:, 1]
    k_hat = torch.tensor([diagnosis["k_hat"][n] for n in FAULT_NAMES], dtype=torch.float64)
    return (k_hat, *calibrated_interval(model, diagnosis))
