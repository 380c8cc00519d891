"""One record through an exported online pipeline and its input contract: the JSON record of ``phm-predict``.

``phm-predict`` reads each CSV into a :class:`~phm_torch.online.corruptions.Record` and calls
:func:`diagnose`; the corruption suite (:mod:`phm_torch.online.corruption_suite`) calls it on records in memory, so both
take the same path. The record's fields are described in :mod:`phm_torch.apps.predict`.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable, Mapping, Sequence
from typing import Any

import torch

from ..faults import FAULT_NAMES
from ..metrics import finite_mean
from ..surrogates.metrics import IDENTIFIED_R2
from .bench_check import BenchCheck
from .bench_lines import Line, find_lines, line_possible, remove_lines
from .corruptions import Record, sample_rate
from .input_contract import InputContract
from .loaded import as_loaded
from .probe_calibration import ProbeCalibration
from .quality import held_out, verdict_error
from .reason_text import reason_lines
from .record_corrections import prepare_record
from .rest_offset_check import offset_limit, offset_std, probe_offset, rest_still
from .timing_check import timing_scan
from .timing_tolerance import TIMING_TOLERANCE_S, read_within_tolerance
from .unexplained_check import checked, residual_floor

# Relative noise always tolerated, whatever the calibration level: the noise estimate of a few noise-free
# heavy-fault records (ringing current) reaches 2.5 %: 1.3-1.5 % of the paper store's records read above this,
# 0.4-0.5 % above 2 %.
NOISE_FLOOR = 0.005


QUANTILES = ("p5", "p50", "p95")


def censor(values: Sequence[float | None], horizon: float) -> tuple[dict[str, float | None], bool]:
    """{p5, p50, p95} with each bound at or beyond ``horizon`` (or NaN / None) as None, and whether any was: a
    bound past the horizon is unknown, never the horizon written as a number."""
    out = {q: (None if v is None or math.isnan(v) or v >= horizon else float(v)) for q, v in zip(QUANTILES, values)}
    return out, any(v is None for v in out.values())


def not_identified(metadata: Mapping[str, Any]) -> list[str]:
    """Fault names whose estimate the pipeline's test command does not identify (R^2 below
    :data:`~phm_torch.surrogates.metrics.IDENTIFIED_R2` on phm-evaluate's held-out records: their k_hat is mostly
    the training prior); [] for a pipeline exported without that measurement."""
    r2 = metadata.get("identifiability") or {}
    return [name for name in FAULT_NAMES if name in r2 and not (r2[name] is not None and r2[name] >= IDENTIFIED_R2)]


SCALE_OFF = 10.0  # a record whose RMS current is this many times the nominal record's (or as many times less)


def scale_message(current: torch.Tensor, nominal: torch.Tensor | None) -> str | None:
    """For a refused record: a line saying that its RMS current (n_full,) [A] is ``SCALE_OFF`` or more times off the
    nominal record's (another actuator, a probe's range, or the current written in mA), None otherwise. The flags
    of such a record (gappy residual, consistency) name a symptom, not the cause."""
    if nominal is None or current.shape != nominal.shape:
        return None
    rms = float(finite_mean(current.double().pow(2)).sqrt())
    ratio = rms / float(nominal.double().pow(2).mean().sqrt())
    if not math.isfinite(ratio) or 1.0 / SCALE_OFF < ratio < SCALE_OFF:
        return None
    units = " (the current written in mA? name the column 'current [mA]')" if 500.0 <= ratio <= 2000.0 else ""
    return (
        f"the current's RMS is {ratio:.3g} x the nominal record's: a record of another actuator or test, a probe's "
        f"range or units{units}, or this actuator far past the faults it was trained on (a current-limited run)"
    )


def remove_probe_offset(
    model: Any, current: torch.Tensor, bench_nominal: torch.Tensor | None, step: Any, nominal: torch.Tensor | None
) -> tuple[Any, float | None, float | None]:
    """The pipeline's step of a record (1, n_full) [A] without the probe offset its rest window shows
    (:func:`~.rest_offset_check.probe_offset`), where the answer without it is in distribution and either near nominal
    or the offset one the ``offset`` check would pass over a still window (:func:`~.rest_offset_check.rest_still`: a
    constant shift, which neither a shorted pair's rest current nor a wandering baseline makes), and that offset and
    its standard deviation [A] (the rest window mean's noise); else the step as it came and None, None.

    Without a shorted pair the rest window sits on the nominal record within 0.5 % of its RMS (noise-free HF records
    of three actuators' stores: 0.41 % at most over 700 reference records, 0.42 % over 2,000 of the 270 V rudder's,
    0.46 % over 700 of a 28 V trim actuator's); a shorted pair's spreads it by 0.7-2.2 times its mean. Near nominal a
    probe offset of 2-5 % of the RMS current (under the ``offset`` check's 5 %) moved the readings several times
    their error (100 life histories with a random offset within +-5 % per record tracked at 21 % coverage); on a
    faulty record it moved k_hat out of its interval unflagged. Removed only near nominal before 2026-11-30: a 2 %
    offset then left 194 of 500 val-like answers of the pretrained pipeline wrong, unflagged (51 clean). One the
    ``offset`` check would refuse (above 5 %) is still removed only where the answer without it is near nominal: a
    mains hum at its crest is as still over the rest window (0.5-2.4 ms) as an offset, and a larger one is better
    refused than read."""
    if nominal is None:
        return step, None, None
    seen = current[0].double() if bench_nominal is None else current[0].double() - (bench_nominal.double() - nominal)
    sigma = float(step.noise[0]) * float(finite_mean(seen.pow(2)).sqrt())
    if bench_nominal is not None:  # seen holds the bench's healthy record's noise as well as this record's
        sigma *= math.sqrt(2.0)
    sigma = 0.0 if math.isnan(sigma) else sigma
    offset = probe_offset(seen, nominal, sigma)
    if offset is None:
        return step, None, None
    corrected = model.run(current - offset, bench_nominal)
    if bool(corrected.ood[0]):
        return step, None, None
    # near nominal as before 2026-11-30 (the near-nominal checks then read the record: coloured noise is `unexplained`);
    # elsewhere only an offset the offset check would pass, over a still window: over a short rest window a 50 Hz hum
    # at its crest is a still shift too (a 20 % hum read as a 15 % offset, removed, answered wrong unflagged)
    near = checked(corrected.k_hat[0], model.nominal, model.interval_mask)
    if near or (abs(offset) <= offset_limit(nominal, sigma) and rest_still(seen, nominal, sigma)):
        return corrected, offset, offset_std(nominal, sigma)
    return step, None, None


def remove_bench_lines(
    model: Any, time: torch.Tensor, current: torch.Tensor, bench_nominal: torch.Tensor | None, step: Any
) -> tuple[Any, torch.Tensor, list[Line], list[Line]]:
    """The pipeline's step of a record (1, n_full) [A] sampled at ``time`` (n_full,) [s] without its bench lines
    (:func:`~.bench_lines.find_lines`: mains hum on the probe), where the answer without them has no fault that makes
    such a line itself (:func:`~.bench_lines.line_possible`: a backlash limit cycle, two shorted phases), and the
    record it read; else the step and record as they came. Also the lines removed and the lines left.

    Hum is no fault of the actuator, and the FDI reads it as one: a 400 Hz hum of 20 % of the RMS current moved every
    answer of the reference's corruption suite out of its interval, unflagged."""
    rate = sample_rate(time)
    if not rate > 0:
        return step, current, [], []
    lines = find_lines(current[0], rate)
    if not lines:
        return step, current, [], []
    cleaned = remove_lines(current[0], time, lines).reshape(current.shape)
    corrected = model.run(cleaned, bench_nominal)
    if line_possible(corrected.k_hat[0]):
        return step, current, [], lines
    return corrected, cleaned, lines, []


def contract_for(
    model: Any, metadata: Mapping[str, Any], command: Callable[[torch.Tensor], torch.Tensor] | None
) -> InputContract:
    """The input contract of an exported pipeline (:meth:`InputContract.of`), with the ``unexplained`` check's
    floor: the pipeline's gappy residual of its own nominal record (one run; :mod:`.unexplained_check`)."""
    contract = InputContract.of(model, metadata, command)
    loaded = as_loaded(model)
    return dataclasses.replace(
        contract, residual_floor=residual_floor(loaded.run, getattr(loaded, "nominal_record", None))
    )


def calibrated_interval(model: Any, diagnosis: Mapping[str, Any]) -> tuple[torch.Tensor, torch.Tensor]:
    """(lower, upper) (8,) float64 of a diagnosis's k_hat: its reported ``k_interval``, or where the diagnosis
    reports none (out of distribution) the calibrated one recomputed at its noise (the answer the flag withheld)."""
    if diagnosis.get("k_interval") is not None:
        bounds = torch.tensor([diagnosis["k_interval"][n] for n in FAULT_NAMES], dtype=torch.float64)
        return bounds[:, 0], bounds[:, 1]
    k_hat = torch.tensor([[diagnosis["k_hat"][n] for n in FAULT_NAMES]], dtype=model.k_half_widths.dtype)
    noise = diagnosis.get("noise")
    with torch.no_grad():
        args = (k_hat,)
        if noise is not None and "noise" in str(model.k_interval.schema):
            args += (torch.tensor([noise], dtype=k_hat.dtype),)
        lower, upper = model.k_interval(*args)
    return lower[0].to(torch.float64), upper[0].to(torch.float64)


def diagnose(
    model: Any,
    record: Record,
    contract: InputContract,
    bench_nominal: torch.Tensor | None = None,
    bench: BenchCheck | None = None,
    keep_current: bool = False,
    probe: ProbeCalibration | None = None,
    remove_lines: bool = True,
    timing_tolerance_s: float = TIMING_TOLERANCE_S,
) -> dict[str, Any]:
    """The diagnosis of one record by the exported pipeline ``model``, as a JSON-able dict (with ``keep_current``,
    also ``"current"``: the (1, n_full) record the pipeline read, aligned and rebased, a tensor for the caller).

    Args:
        model: the pipeline: a :class:`~.loaded.LoadedPipeline` of any format (:func:`~.loaded.load_pipeline`),
            or a scripted / eager ``OnlinePipeline``.
        record: its current (n_full,) [A] (NaN = missing), with its command and position (``None``: a
            current-only record, whose command and tracking checks are skipped).
        contract: the pipeline's :class:`InputContract`.
        bench_nominal: (n_full,) [A] healthy record of the measuring bench (phm-predict's ``baseline``), or None.
        bench: :func:`~.bench_check.check_bench` of that record (once per bench); a bench it finds too far from
            the training model makes the record out of distribution with the reason ``bench``.
        probe: the bench's probe calibration (:func:`~.probe_calibration.fit_probe` of its healthy record, which
            ``bench_nominal`` then is read through): the record's current is read through it too.
        remove_lines: False reads a record with its bench lines (:func:`remove_bench_lines`; to measure what their
            removal does).
        timing_tolerance_s: the current's timing tolerance [s] (a current-only record's trigger; with the command
            column, the current channel's own lag): its k intervals hold every reading within it
            (:mod:`.timing_tolerance`; 0: the timing is exact).
    """
    model = as_loaded(model)
    measured = record.current
    record, fixed = prepare_record(record, contract.command, contract.nominal)
    if probe is not None:
        record = Record(record.time, record.command, record.position, probe.apply(record.current))
    current = torch.as_tensor(record.current, dtype=model.dtype).reshape(1, -1)
    step = model.run(current, bench_nominal)
    step, current, lines, lines_left = (
        remove_bench_lines(model, record.time, current, bench_nominal, step)
        if remove_lines
        else (step, current, [], [])
    )
    if lines:
        record = Record(record.time, record.command, record.position, current[0].to(record.current.dtype))
    step, offset, offset_error = remove_probe_offset(model, current, bench_nominal, step, contract.nominal)
    read = current if offset is None else current - offset  # what the step read, before any rebase
    k_hat, score, rul, ood, resid, current = step.k_hat, step.score, step.rul, step.ood, step.residual, step.current
    noise, p_faulty = float(step.noise[0]), float(step.p_faulty[0])  # noise as measured, before the baseline
    bounds = None if step.k_lower is None else torch.stack([step.k_lower, step.k_upper], -1)[0]
    reference = float(getattr(model, "calibration_noise", float("nan")))
    noisy = None if math.isnan(reference) or math.isnan(noise) else noise > max(2.0 * reference, NOISE_FLOOR)
    checks = contract.check(
        model, record, current[0], noise, bool(ood[0]), k_hat[0], bool(score[0] > 0), measured, float(resid[0])
    )
    checks.messages.extend(fixed.messages())
    if lines:
        checks.messages.append(
            f"a line through the whole record at {', '.join(line.text() for line in lines)} (hum on the bench's "
            "probe; the answer without it has no fault that makes one): removed"
        )
    if lines_left:
        checks.messages.append(
            f"a line through the whole record at {', '.join(line.text() for line in lines_left)}: left in, as the "
            "answer without it has a fault that can make one (a backlash limit cycle, two shorted phases); if the "
            "bench hums at that frequency, remove the hum there"
        )
    if offset is not None:
        checks.messages.append(
            f"the current sat {offset:+.4g} A off the nominal record at rest (a probe's offset: the answer without "
            "it near nominal, or the shift small and still there, which no fault's rest current is): removed"
        )
    if bench is not None and not bench.ok:
        checks.reasons.append("bench")
        checks.messages.append(bench.message())
    # the current's timing against the pipeline's own answer (a current-only record's trigger offset, a current
    # delayed alone); with a baseline the rebased record carries its noise too: each shift's own estimate
    timing = None
    if contract.timing_ratio is not None:  # a pipeline without its own threshold is not scanned (timing_check.py)
        timing = timing_scan(model, current[0], noise if bench_nominal is None else math.nan)
    if timing is None:
        checks.skipped.append("timing")
    elif timing.off(model.sample_rate, contract.timing_ratio):
        checks.reasons.append("timing")
        checks.messages.append(timing.message(model.sample_rate))
    out = bool(checks.reasons)
    checks.messages.extend(reason_lines(checks.reasons))
    if out and (scale := scale_message(current[0], contract.nominal)) is not None:
        checks.messages.append(scale)
    trusted_bounds = bounds is not None and not out and bool(torch.isfinite(bounds).all())
    tolerance = None
    if trusted_bounds and timing_tolerance_s > 0:
        # beyond the tolerance, the scan's best shift (the record not refused: a timing the data allow)
        widen = timing is not None and timing.widens(model.sample_rate, timing_tolerance_s)
        tolerance = read_within_tolerance(
            model,
            read[0],
            model.sample_rate,
            timing_tolerance_s,
            bench_nominal,
            record.command is None,
            timing.shift if widen else None,
        )
    if tolerance is not None:
        bounds = torch.stack(
            [
                torch.minimum(bounds[:, 0].double(), tolerance.lower),
                torch.maximum(bounds[:, 1].double(), tolerance.upper),
            ],
            -1,
        )
        for line in (tolerance.widened_message(), tolerance.message()):
            if line is not None:
                checks.messages.append(line)
    r = rul[0].tolist()
    censored = out or any(math.isnan(v) for v in r)
    rul_hours, rul_censored = (None, False) if censored else censor(r, model.horizon_hours)
    command = checks.command
    return {
        "k_hat": dict(zip(FAULT_NAMES, k_hat[0].tolist())),
        "k_interval": dict(zip(FAULT_NAMES, bounds.tolist())) if trusted_bounds else None,
        "health_score": float(score[0]),
        "healthy": bool(score[0] > 0),
        "p_faulty": None if out or math.isnan(p_faulty) else p_faulty,
        "rul_hours": rul_hours,
        "rul_censored": rul_censored,
        "verdict_held_out_error": None if out else verdict_error(held_out(model.metadata), bool(score[0] > 0)),
        "k_not_identified": not_identified(model.metadata),
        "out_of_distribution": out,
        "ood_reasons": checks.reasons,
        "checks_skipped": checks.skipped,
        "residual": float(resid[0]),
        "command_check": None
        if command is None
        else {"nrmse": command.nrmse, "best_lag_s": command.best_lag_s, "gain": command.gain, "ok": command.ok},
        "tracking_check": checks.tracking,
        "trigger_offset_s": fixed.trigger_offset_s,
        "timing_tolerance": None if tolerance is None else tolerance.as_dict(),
        "timing_check": None
        if timing is None
        else {
            "best_shift_s": timing.lag_s(model.sample_rate),
            "ratio": timing.ratio,
            "ok": "timing" not in checks.reasons,
        },
        "clock_error": fixed.clock_error,
        "bench_lines": [dataclasses.asdict(line) for line in lines],
        "probe_offset": offset,
        "probe_offset_std": offset_error,
        "current_reversed": fixed.current_correlation is not None,
        "position_reversed": fixed.position_correlation is not None,
        "noise": None if math.isnan(noise) else noise,
        "noise_above_calibration": noisy,
        "messages": checks.messages,
        **({"current": current} if keep_current else {}),
    }
