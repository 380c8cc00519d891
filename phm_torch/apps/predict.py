"""``phm-predict``: the exported online pipeline on measurement CSVs -> JSON (one record per file).

Each record holds:

* ``k_hat`` {fault name: value} and ``k_interval`` {fault name: [lower, upper]}: per-parameter intervals of
  the actual k, 90 % coverage each by default, calibrated by phm-evaluate at several noise levels and
  taken at the record's estimated noise (``null`` out of distribution or for a pipeline exported without
  them), the union over the readings within ``timing_tolerance`` (1 ms by default; 0: an exact timing) of the
  current's timing (a current-only record's trigger, which nothing aligns; with the command column, the current
  channel's own lag) and, where the timing scan finds the record explained markedly better further off (below
  refusal), around that shift too; with ``timing_tolerance`` {``tolerance_s``, ``readings``, ``verdict_stable``,
  ``healthy_share``, ``widened_to_s``} (:mod:`phm_torch.online.timing_tolerance`; ``null`` otherwise) and a line
  in ``messages`` where the verdict changes within them or the intervals were widened beyond the tolerance;
* ``health_score`` (> 0 healthy; the pipeline's verdict score, from the verdict classifier of FDI
  estimates when the bundle has one), ``healthy`` and ``p_faulty``, the probability that the actuator is faulty
  given that score, calibrated on held-out records by phm-evaluate (``null`` out of distribution);
* ``rul_hours`` {p5, p50, p95} (``null`` out of distribution: never a confident RUL from garbage); a bound
  beyond the pipeline's horizon is ``null`` with ``rul_censored`` true, never the horizon written as a number;
* ``verdict_held_out_error``: how often a verdict of this kind was wrong on phm-evaluate's held-out records of this
  actuator and command (a healthy verdict: the share of faulty records answered healthy; a faulty one: the share of
  healthy ones answered faulty; ``null`` out of distribution or for a pipeline exported without that measurement);
  the run warns once where either passes 10 % (:mod:`phm_torch.online.quality`);
* ``k_not_identified``: the components the pipeline's test command does not identify (R^2 below 0.25 on
  phm-evaluate's held-out records): their ``k_hat`` is mostly the training prior, not a measurement;
* ``out_of_distribution`` and the gappy ``residual`` [A];
* ``noise``, the estimated relative measurement noise (noise std over the record's RMS current, before any
  baseline), and ``noise_above_calibration``: more than twice the noise of the records P(faulty) and the
  RUL band were calibrated on, and above ``NOISE_FLOOR`` (they are then too narrow, and so are the
  intervals above their highest calibrated level; ``null`` when the pipeline does not know that level);
* ``ood_reasons``, every check of the input contract that fired (:mod:`phm_torch.online.input_contract`:
  the pipeline's own checks by name, ``command``, ``tracking``, ``sign``, ``offset``, ``shape``, ``noise``,
  ``spikes``, ``gap``, ``stuck``, ``held``, ``bench``, ``timing``), ``checks_skipped`` (``command`` and ``tracking``
  for a CSV without command or position columns, a current-only record; ``timing`` for a pipeline without its own
  threshold or a format without the consistency statistic), ``command_check``, ``tracking_check``, ``timing_check``
  (the shift [s] at which the pipeline's own answer explains the record best, how many times better than unshifted,
  and whether the check passed: :mod:`phm_torch.online.timing_check`) and ``messages`` (one line per failed check);
* what was corrected before the pipeline read the record, each said in ``messages``: ``bench_lines`` (sinusoids of
  one frequency, amplitude and phase through the whole record, hum on the probe, removed where the answer without
  them has no fault that makes one: :mod:`phm_torch.online.bench_lines`; each with ``frequency`` [Hz],
  ``amplitude`` [A], ``phase`` [rad] and ``share`` of the RMS current), ``probe_offset`` [A] (an offset
  read over the rest window and removed where the answer without it is near nominal) with ``probe_offset_std`` [A]
  (its own error: the window mean's noise), ``clock_error`` (a logger's
  relative clock error undone by resampling, from the record's command column; ``null`` without one),
  ``trigger_offset_s`` (the shift
  onto the test command's grid found by the record's command column; ``null`` without one) and ``current_reversed``
  (a current probe the wrong way round: the current's mean of the other sign than the nominal record's and its
  shape anti-correlated with it, read as -current; the ``baseline`` records likewise), ``position_reversed`` (a
  position anti-correlated with the command column: a sensor the wrong way round, read as -position and then
  checked as any position is); with a ``baseline`` whose
  difference from the nominal record is a probe's gain and offset, every record is read through the inverse map
  (:mod:`phm_torch.online.probe_calibration`; the metrics' ``probe_calibration``).

The record is computed by :func:`phm_torch.online.diagnosis.diagnose`.

The model is a file written by ``phm-evaluate`` or ``phm-export`` in any of its formats (TorchScript ``.pt``,
torch.export ``.pt2``, AOTInductor ``.aoti.pt2``, ONNX ``.onnx.zip`` (complete records only); :mod:`phm_torch.online.formats`), the format read from the
file (``format=`` insists on one); the JSON is the same for every format (no unpickling), but for the ``timing``
check, which reads the TorchScript file's consistency statistic. An empty or ``nan`` cell of a CSV's ``current`` column is a missing
sample, which the pipeline drops (too many, and the record is out of distribution). With ``baseline`` (healthy records of the measuring bench), every
measurement is first moved onto the training model by the difference between that bench's healthy record
and the training model's; that healthy record, read as measured, must land within ``BENCH_TOLERANCE`` interval
half-widths of nominal, else the bench differs too much for a baseline to correct and every record is out of
distribution with the reason ``bench`` (:mod:`phm_torch.online.bench_check`; the metrics' ``bench_check``).
"""

from __future__ import annotations

import dataclasses
import json
import logging
import math
from collections.abc import Callable
from pathlib import Path
from typing import Any

import hydra
import numpy as np
import torch
from omegaconf import DictConfig

from .. import provenance
from ..io import read_measurement
from ..io.measurement_csv import Measurement
from ..online.bench_check import check_bench
from ..online.bench_lines import find_lines, remove_lines
from ..online.corruptions import Record
from ..online.diagnosis import NOISE_FLOOR, contract_for, diagnose
from ..online.loaded import LoadedPipeline, UnservedRecord, load_pipeline
from ..online.probe_calibration import ProbeCalibration, fit_probe
from ..online.quality import held_out, quality_warnings
from ..online.record_corrections import polarity_reversal
from ..online.timing_tolerance import tolerance_seconds
from . import common

log = logging.getLogger(__name__)

__all__ = ["NOISE_FLOOR", "predict"]
LENGTH_TOLERANCE = 0.01  # fraction of the test record a measurement may be shorter or longer by


def _paths(value: Any, name: str) -> list[str]:
    paths = common.plain(value)
    paths = [paths] if isinstance(paths, str) else paths
    if not isinstance(paths, list) or not paths or not all(isinstance(p, str) for p in paths):
        raise ValueError(f"{name} must be a CSV path or a list of paths, got {paths!r}")
    return paths


def _current(path: str, model: LoadedPipeline, resample: bool) -> torch.Tensor:
    """The envelope current (1, n_full) [A] of one measurement CSV (see :func:`_read`)."""
    return _read(path, model, resample)[0]


def _read(path: str, model: LoadedPipeline, resample: bool) -> tuple[torch.Tensor, Any]:
    """The envelope current (1, n_full) [A] of one measurement CSV, in the pipeline's dtype.

    The record's first sample is taken as the start of the test command, as for a record of the right
    length. One longer or shorter than the test record by at most ``LENGTH_TOLERANCE`` of it (another
    implementation may stop one sample early or late) is cut to length, or its tail is marked missing (NaN:
    the gappy layer drops those samples), with a warning; a larger difference is an error naming the file."""
    m = read_measurement(
        path,
        expected_rate=float(model.sample_rate),
        resample=resample,
        missing_ok=("current",),
        optional=("command", "position"),
    )
    m = _test_window(m, int(model.n_full), path)
    current = torch.as_tensor(m.current, dtype=model.dtype).unsqueeze(0)
    n, n_full = current.shape[1], int(model.n_full)
    if n == n_full:
        return current, m
    if abs(n - n_full) > LENGTH_TOLERANCE * n_full:
        raise ValueError(
            f"{path}: current has {n} samples; the model expects {n_full} (the full test record; "
            f"within {LENGTH_TOLERANCE:.0%} of that length the record is cut or its tail marked missing; a record "
            "with a pre-trigger buffer, samples at negative times and one at t = 0, is cut to the test from t = 0)"
        )
    log.warning(
        "%s: %d samples instead of %d: %s",
        path,
        n,
        n_full,
        "the tail beyond the test record is dropped" if n > n_full else "the missing tail is marked missing",
    )
    if n > n_full:
        return current[:, :n_full], m
    return torch.cat([current, current.new_full((1, n_full - n), float("nan"))], 1), m


def _test_window(m: Measurement, n_full: int, path: str) -> Measurement:
    """The measurement cut to the test record where its time column places the test's start: a bench that keeps a
    pre-trigger buffer writes samples at negative times and the trigger at t = 0, and may log on after the test. With
    samples before t = 0 and one within half a step of it, the ``n_full`` samples from it are kept (fewer where the
    record ends first); a record whose time starts at 0 or elsewhere (another origin) is read from its first sample."""
    step = 1.0 / m.sample_rate
    i0 = int(np.argmin(np.abs(m.time)))
    if abs(float(m.time[i0])) > 0.5 * step or i0 == 0:
        # no samples before t = 0: no evidence of a triggered acquisition, and a longer record from t = 0 may be
        # another test (another actuator's, 15,001 samples, would be cut and read): the length rule below decides
        return m
    window = slice(i0, i0 + n_full)
    log.warning(
        "%s: the test window is cut from the record by its time column: %d samples before t = 0 and %d after the "
        "test's %d dropped",
        path,
        i0,
        max(0, len(m) - i0 - n_full),
        n_full,
    )
    return dataclasses.replace(
        m,
        time=m.time[window],
        command=m.command[window],
        position=m.position[window],
        current=m.current[window],
        extra={name: x[window] for name, x in m.extra.items()},
    )


def _pipeline_command(
    cfg: DictConfig, metadata: dict[str, Any], model_path: Path
) -> tuple[dict[str, Any], Callable[[torch.Tensor], torch.Tensor] | None]:
    """The pipeline's provenance (from its ``metadata``, checked against an explicit ``actuator=``/``command=``)
    and its test command (``None`` for a pipeline exported before it recorded one)."""
    prov = common.reconcile_provenance(cfg, metadata.get("provenance"), f"pipeline {model_path}")
    if prov["command"] is None:
        log.warning("%s records no test command: the records' command columns are not checked", model_path)
        return prov, None
    return prov, common.command(prov["command"]["params"])


def _record(m: Any, current: torch.Tensor) -> Record:
    """The measurement as a record of the test's length (command and position ``None`` when the CSV lacks them)."""
    n = min(len(m.time), current.shape[1])
    column = lambda x: None if np.isnan(x).all() else torch.as_tensor(x[:n], dtype=torch.float64)
    return Record(torch.as_tensor(m.time[:n], dtype=torch.float64), column(m.command), column(m.position), current[0])


def _bench_nominal(cfg: DictConfig, model: LoadedPipeline) -> tuple[torch.Tensor | None, ProbeCalibration | None]:
    """The mean of the ``baseline`` records (healthy records of the measuring bench), read through the probe
    calibration it shows (:mod:`phm_torch.online.probe_calibration`), and that calibration; (None, None) without."""
    if cfg.get("baseline") is None:
        return None, None
    if not model.can_rebase:
        raise ValueError(
            f"baseline: the pipeline {str(cfg.pipeline)!r} holds no nominal record of its training "
            f"model (exported before baselines existed, or trained on a store without a nominal split)"
        )
    records = []
    for path in _paths(cfg.baseline, "baseline"):
        current = _current(path, model, bool(cfg.resample))[0]
        corr = polarity_reversal(current, model.nominal_record)
        if corr is not None:  # the bench's probe turned round: its records are read as -current (diagnose)
            log.warning(
                "baseline %s: the current read reversed (correlation %.2f with the nominal record): read as -current",
                path,
                corr,
            )
            current = -current
        # a healthy record makes no line itself: any line through it is the bench's hum, which would otherwise be
        # subtracted from every record read (whose own lines diagnose removes)
        lines = find_lines(current, float(model.sample_rate))
        if lines:
            log.warning(
                "baseline %s: a line through the record at %s: removed", path, ", ".join(x.text() for x in lines)
            )
            time = torch.arange(current.numel(), dtype=torch.float64) / float(model.sample_rate)
            current = remove_lines(current, time, lines)
        records.append(current)
    mean = torch.stack(records).mean(0)
    probe = fit_probe(mean, model.nominal_record)
    if probe is not None:
        log.warning("%s", probe.message())
        mean = probe.apply(mean)
    return mean, probe


def predict(cfg: DictConfig) -> tuple[dict[str, Any], dict[str, Any]]:
    """Run the exported pipeline ``cfg.pipeline`` on every CSV of ``cfg.measurements`` (moved onto the
    training model with the bench's healthy ``baseline`` records, when given)."""
    paths = _paths(cfg.measurements, "measurements")
    model_path = Path(cfg.pipeline)
    model = load_pipeline(model_path, cfg.get("format"))  # checks the file and its format
    metadata = model.metadata
    prov, command = _pipeline_command(cfg, metadata, model_path)
    if not model.calibrated:
        log.warning("%s was exported before the verdict calibration existed: p_faulty is null", model_path)
    quality = held_out(metadata)
    for line in quality_warnings(quality):
        log.warning("%s: %s", model_path, line)
    tolerance = tolerance_seconds(cfg.get("timing_tolerance"))
    bench_nominal, probe = _bench_nominal(cfg, model)
    if bench_nominal is None and model.can_rebase:
        # a bench differing from the training model by 0.5 % of the current can turn 14 % of the faults
        # into "healthy" verdicts; the rebase restores them (docs/surrogates.md, modelling differences)
        log.warning(
            "no baseline: the measurements are read as records of the training model; on another "
            "bench give baseline=<healthy record(s) of that bench>, since a small modelling difference "
            "moves the verdict (docs/surrogates.md, 'Modelling differences')"
        )
    contract = contract_for(model, metadata, command)
    bench = None if bench_nominal is None else check_bench(model, bench_nominal)
    if bench is not None and not bench.ok:
        log.warning("%s; every record is out of distribution (reason 'bench')", bench.message())
    elif bench is not None and not bench.healthy:  # within tolerance, but a known-healthy record read faulty
        log.warning(
            "the bench's healthy baseline record reads faulty (%s %.1f interval half-widths from nominal): "
            "the verdicts of this bench lean to 'faulty'; check it with phm-workbench",
            bench.worst,
            bench.max_deviation,
        )
    records = []
    for path in paths:
        current, m = _read(path, model, bool(cfg.resample))
        try:
            record = {
                "file": str(path),
                **diagnose(
                    model,
                    _record(m, current),
                    contract,
                    bench_nominal,
                    bench,
                    probe=probe,
                    timing_tolerance_s=tolerance,
                ),
            }
        except UnservedRecord as e:  # a format that serves complete records only (onnx)
            raise UnservedRecord(f"measurements: {str(path)!r}: {e}") from None
        ood = "; the record is out of distribution" if record["out_of_distribution"] else ""
        for message in record["messages"]:  # a correction (a reversed probe read as -current) is answered
            log.warning("%s: %s%s", path, message, ood)
        if record["noise_above_calibration"]:
            levels = getattr(model, "interval_noise", None)
            top = float(levels.max()) if levels is not None and levels.numel() else float("nan")
            intervals = (
                f"the k intervals follow it (calibrated up to {100 * top:.2f} %)"
                if record["noise"] <= top
                else f"so are the k intervals (calibrated up to {100 * top:.2f} %)"
                if math.isfinite(top)
                else "so may be the k intervals"
            )
            log.warning(
                "%s: estimated current noise %.2f %% of its RMS, more than twice the %.2f %% P(faulty) and the RUL "
                "band were calibrated at: they are too narrow; %s",
                path,
                100 * record["noise"],
                100 * float(model.calibration_noise),
                intervals,
            )
        records.append(record)
    if cfg.out:
        common.write_json(Path(cfg.out), records)
    return {
        "files": len(records),
        "out_of_distribution": sum(r["out_of_distribution"] for r in records),
        "baseline": bench_nominal is not None,
        "bench_check": None if bench is None else bench.as_dict(),
        "probe_calibration": None if probe is None else probe.as_dict(),
        "actuator": provenance.describe(prov["actuator"]),
        "command": provenance.describe(prov["command"]),
        "noise_above_calibration": sum(bool(r["noise_above_calibration"]) for r in records),
        "timing_tolerance_s": tolerance,
        "held_out_quality": quality,
    }, {"records": records}


@hydra.main(config_path=common.CONFIG_PATH, config_name="predict", version_base="1.3")
@common.report_errors("phm-predict")
def main(cfg: DictConfig) -> None:
    _, objects = predict(cfg)
    if not cfg.out:
        print(json.dumps(objects["records"], indent=2), flush=True)


if __name__ == "__main__":
    main()
