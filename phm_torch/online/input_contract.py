"""Input contract of an exported online pipeline: may its answer on this record be trusted, and if not, why?

Every check that fires names itself in the record's ``ood_reasons``; ``out_of_distribution`` is their union.

From the pipeline's own out-of-distribution flag, per internal check (:func:`pipeline_reasons`):

* ``missing`` - too few finite selected samples;  ``flat`` - a flat line;
* ``gappy_residual`` - the gappy residual above its threshold at the record's noise (noise_threshold.py);
* ``pod_residual``, ``roughness``, ``plateau`` - the full-record statistics of
  :class:`~phm_torch.surrogates.full_signal_check.FullSignalCheck`;
* ``inconsistent`` - a pipeline with a consistency check (:mod:`.consistency`, analysis by synthesis): the
  record is not the one its own k_hat predicts (its scripted ``consistency(x)`` above 1).

A pipeline whose flag fired for a reason none of these explains (another structure) gives ``pipeline``. phm-predict's
diagnosis adds ``timing`` (:mod:`.timing_check`: the record explained far better by the pipeline's own answer moved
in time) and ``bench`` (:mod:`.bench_check`).

From the record's other columns (skipped, and listed in ``checks_skipped``, for a current-only record):

* ``command`` - the command column is not the pipeline's test command (:mod:`.command_check`);
* ``tracking`` - the position does not follow the command as an actuator of this type can: its tracking
  NRMSE (RMS of position - command over the command's range) outside the range the pipeline's training
  records span, widened by ``TRACKING_MARGIN`` (metadata ``tracking_nrmse``), or, for a pipeline without it,
  above ``TRACKING_NRMSE_MAX`` or with a position range above ``POSITION_GAIN`` x the command's; an answer
  the pipeline calls healthy is held to the healthy training records' range (``tracking_nrmse_healthy``); a
  position anti-correlated with the command (below ``REVERSED_CORRELATION``) is a reversed sensor.

From the current, against the noise calibration and the training model's nominal record (``nominal_record``):

* ``noise`` - the estimated noise above ``NOISE_MARGIN`` x the highest level the intervals were calibrated at;
* ``sign`` - the record's mean current has the other sign than the nominal record's (a probe the wrong way
  round; the envelope current of any fault vector keeps its sign);
* ``overcurrent`` - the current exceeds the drive range the FDI was trained within (``current_bound``): a record a
  protected drive would not have finished (two nearly shorted phases), or a probe scaled wrong;
* ``stuck`` - the current holds one exact value for ``STUCK_RUN`` of the record (``STUCK_MIN`` samples at least) or
  longer (a stuck sensor, a burst of zeros) while it moves everywhere else (at most ``MOVING_SHARE`` equal neighbours
  outside that run), a leading run (an actuator at rest before the recorder's trigger) aside;
* ``gap`` - ``STUCK_RUN`` of the record or more missing in one stretch (a logger's dropout): the FDI and its
  intervals were trained and calibrated with a few scattered missing samples, and a gap takes out a whole stretch
  of the chirp (5 % gaps moved k_hat out of its interval on 4 of 8 corrupted records, unflagged);
* ``held`` - ``HELD_SHARE`` or more of its consecutive samples are equal and nearly all its changes fall every
  k-th sample (data decimated by k and held). Over 2,500 noise-free HF records of the paper store the longest run
  of equal samples is 4 and the share of equal neighbours at most 0.08 %; written at a resolution of 0.1-10 mA
  they repeat values everywhere, and a noisy record read by a coarse ADC does too: neither is flagged (their
  changes fall anywhere, and no single run stands out);
* and, for a record whose estimate k_hat is near nominal (the checks a near-nominal answer must pass: its
  record must look like the nominal one), counted in large faults as the intervals count them
  (``|k_hat - k_0| > interval_level``, the phase k7 left out):
  * ``offset`` (unless two phases read shorted at 0.4 or more) - over the rest window (the leading samples where the
    nominal record has not left zero yet: the actuator at rest) the record sits off the nominal record
    (:mod:`.rest_offset_check`); listed in ``checks_skipped`` for a command that moves at once (no rest window);
  * ``unexplained`` (every damage within 0.1 of nominal) - the pipeline's gappy residual above what the model's
    own floor and the record's estimated white noise explain (:mod:`.unexplained_check`: coloured noise, hum);
  * ``shape`` (no large fault) - the record's correlation with the nominal record below ``SHAPE_MIN``, or below
    the pipeline's own calibrated threshold (``shape_correlation_min``, :func:`calibrate_shape_min`) when lower;
  * ``spikes`` (no large fault) - a second difference far above the record's noise and above the steps the
    filtered current takes itself (:mod:`.spike_check`; the pipeline's own ``spike_step_max`` when higher).

A record whose k_hat has large faults skips the shape and spike comparisons: heavy faults reshape the record (24
val-like vectors: correlation with the nominal record down to 0.22); the consistency of such an answer is the
forward surrogate's (``inconsistent``). The rest window stays the nominal one's under any fault but a heavily
shorted pair (:mod:`.rest_offset_check`; the 0.9 of its RMS measured once came from two phases shorted at 0.8 and
0.63). The thresholds were measured on clean records of the reference actuator (``scripts/corruption_suite.py``,
docs/prognostics.md): over 24 random fault vectors at 0-3 % noise, records with no large fault in k_hat correlate
>= 0.968 with the nominal one and sit within 0.012 of its RMS over the rest window.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Any

import torch

from ..drive_range import within_drive_range
from ..metrics import finite_mean, nrmse
from .command_check import CommandCheck, check_command, unit_hint
from .corruptions import Record, sample_rate
from .fault_count import large_faults, no_large_fault
from .rest_offset_check import REST_MIN, rest_offset, rest_window
from .run_checks import run_reasons
from .spike_check import SPIKE_STEP, has_spikes
from .timing_check import TIMING_RATIO
from .unexplained_check import UNEXPLAINED_RATIO, checked, unexplained_ratio

PIPELINE_CHECKS = ("missing", "flat", "gappy_residual", "pod_residual", "roughness", "plateau", "inconsistent")
# a position anti-correlated with its command is a reversed sensor; a stalled actuator (a double short stops it)
# correlates near 0 either way, the val records of the paper store 0.82 and above
REVERSED_CORRELATION = -0.5
TRACKING_MARGIN = 1.5  # the training range of the tracking NRMSE, widened by this factor on both sides
# without a training range: a loop that follows its command with at most 90 deg of lag at equal amplitude
# (its bandwidth covers the test command) misses it by |1 - e^{-j pi/2}| A / sqrt(2) over a range 2 A: 0.5
TRACKING_NRMSE_MAX = 0.5
# position range over the command's range: a loop does not move its load twice as far as commanded (no lower
# bound: a heavy fault can stall the actuator, position range 0.09 x the command's on a paper-sampled vector)
POSITION_GAIN = 2.0
SHAPE_MIN = 0.9  # correlation with the nominal record (the most a calibrated pipeline's own threshold may be)
SHAPE_MARGIN = 1.5  # a calibrated threshold: 1 - this x (1 - the lowest correlation of the held-out records)
NOISE_MAX = 0.1  # relative noise limit of a pipeline that does not record its calibrated levels
NOISE_MARGIN = 1.5  # the intervals are held at their highest calibrated level up to this factor above it
MIN_PRESENT = 0.9  # a command or position column is checked on its finite samples if at least this share is finite


@dataclass(frozen=True)
class ContractChecks:
    """Outcome of :meth:`InputContract.check` for one record."""

    reasons: list[str]
    skipped: list[str]
    command: CommandCheck | None
    tracking: dict[str, Any] | None
    messages: list[str] = field(default_factory=list)


def calibrate_shape_min(model: Any, signals: torch.Tensor, k_hat: torch.Tensor) -> float | None:
    """The ``shape`` check's threshold for a pipeline, from held-out records (B, n_full) [A] and its estimates
    k_hat (B, 8): 1 - SHAPE_MARGIN x (1 - the lowest correlation with the nominal record among the records whose
    estimate has no large fault), at most SHAPE_MIN. SHAPE_MIN was measured on the reference actuator (>= 0.968);
    the 270 V rudder's clean near-nominal records go lower, and 1.1 % of them were refused. None: nothing to
    calibrate on (no nominal record, or no such record)."""
    nominal = getattr(model, "nominal_record", None)
    if nominal is None or signals.shape[0] == 0 or nominal.numel() != signals.shape[1]:
        return None
    none_large = no_large_fault(model, k_hat)
    if not bool(none_large.any()):
        return None
    corr = nominal_correlation(signals[none_large].double(), nominal.double())
    return min(SHAPE_MIN, 1.0 - SHAPE_MARGIN * (1.0 - float(corr.min())))


def nominal_correlation(x: torch.Tensor, nominal: torch.Tensor) -> torch.Tensor:
    """Correlation (B,) (or () for one record) of records x (B, n) or (n,) [A] with the nominal record (n,) [A],
    a missing sample taking the nominal value; 0 for a constant record. The ``shape`` check and its calibration."""
    x = torch.where(torch.isfinite(x), x, nominal)
    xc, nc = x - x.mean(-1, keepdim=True), nominal - nominal.mean()
    return (xc @ nc) / (xc.norm(dim=-1) * nc.norm()).clamp(min=1e-300)


def pipeline_reasons(model: Any, x: torch.Tensor) -> list[list[str]] | None:
    """Which of ``PIPELINE_CHECKS`` fire for each record x (B, n_full) or (B, n_points) [A] as the pipeline saw it
    (after any rebase); ``None`` for a pipeline whose internals are not those of ``OnlinePipeline``.

    Recomputed from the scripted pipeline's submodules and attributes, the same statistics and thresholds as
    its forward; works for pipelines exported before this module existed (the shipped pretrained one). A loaded
    pipeline of another format (:class:`~.loaded.LoadedPipeline`) answers from its own outputs.
    """
    if callable(getattr(type(model), "pipeline_reasons", None)):
        return model.pipeline_reasons(x)
    try:
        gappy, min_count, threshold = model.gappy, int(model.min_count), float(model.residual_threshold)
        full = x.shape[1] == int(model.n_full)
        samples = (x.index_select(1, gappy.indices) if full else x).to(gappy.modes_hat.dtype)
        check = model.full_check if full and bool(model.has_full_check) else None
    except (AttributeError, RuntimeError):
        return None
    valid = torch.isfinite(samples)
    enough = valid.sum(1) >= min_count
    filled = torch.where(enough.unsqueeze(1) & valid, samples, gappy.mean_hat.expand_as(samples))
    with torch.no_grad():
        _, residual = gappy(filled, torch.where(enough.unsqueeze(1), valid, torch.ones_like(valid)))
        low, high = torch.aminmax(torch.where(valid, samples, samples.nanmean(1, keepdim=True)), dim=1)
        flat = (
            (high - low) < 1e-6
            if bool(valid.all())
            else torch.where(valid, samples, torch.zeros_like(samples)).std(1) < 1e-6
        )  # as the forward decides
        if hasattr(model, "gappy_residual_limit"):  # per record, at its noise (noise_threshold.py)
            threshold = model.gappy_residual_limit(x)
        flags = {"missing": ~enough, "flat": flat, "gappy_residual": (residual > threshold) | ~torch.isfinite(residual)}
        if check is not None:
            flags["pod_residual"] = check.residual(x) > float(check.residual_threshold)
            flags["roughness"] = check.roughness(x) > float(check.roughness_threshold)
            flags["plateau"] = check.plateau(x) > float(check.plateau_threshold)
        if bool(getattr(model, "has_consistency", False)):
            flags["inconsistent"] = model.consistency(x) > 1.0  # NaN (no finite sample) compares False
    return [[name for name in PIPELINE_CHECKS if name in flags and bool(flags[name][i])] for i in range(x.shape[0])]


def tracking_nrmse(command: torch.Tensor, position: torch.Tensor) -> float:
    """RMS of (position - command) over the command's range: how closely the position follows the command."""
    return float(nrmse(position.double().flatten(), command.double().flatten()))  # NaN for a constant command


def tracking_range(command: torch.Tensor, positions: torch.Tensor) -> list[float]:
    """[min, max] tracking NRMSE of records' positions (B, n) [rad] against their command (n,) [rad]: what
    phm-evaluate records in the exported pipeline's metadata (``tracking_nrmse``) from a store's split."""
    command, positions = command.double().flatten(), positions.double()
    if positions.dim() != 2 or positions.shape[1] != command.numel() or positions.shape[0] == 0:
        raise ValueError(f"tracking_range: positions must be (B, {command.numel()}), got {tuple(positions.shape)}")
    values = nrmse(positions.double(), command.double().expand_as(positions))
    return [float(values.min()), float(values.max())]


def _range(metadata: Mapping[str, Any], key: str) -> tuple[float, float] | None:
    """A [low, high] tracking NRMSE range of the pipeline's metadata (None when absent)."""
    value = metadata.get(key)
    if value is None:
        return None
    if not (isinstance(value, (list, tuple)) and len(value) == 2 and 0 <= value[0] <= value[1]):
        raise ValueError(f"{key}: expected [low, high] with 0 <= low <= high, got {value!r}")
    return float(value[0]), float(value[1])


@dataclass(frozen=True)
class InputContract:
    """What a record must satisfy for the pipeline's answer to be trusted.

    Args:
        command: the pipeline's test command, time [s] -> [rad] (None: the command column is not checked).
        tracking_range: (low, high) tracking NRMSE of the pipeline's training records (None: the physical bound).
        noise_max: relative noise above which the record is out of distribution.
        nominal: the pipeline's nominal record (n_full,) [A] (None: the checks against it are skipped).
        tracking_range_healthy: (low, high) tracking NRMSE of the healthy training records, for a record the
            pipeline calls healthy (None: ``tracking_range``).
        current_bound: [A] the drive range the pipeline's FDI was trained within (metadata ``drive_current_bound``:
            phm-train's ``drive_range`` x the actuator's current limit). A record whose current exceeds it is
            ``overcurrent``: a protected drive would have tripped, and the FDI never saw such a record (None: the
            check is skipped, as for a pipeline trained before it).
    """

    command: Callable[[torch.Tensor], torch.Tensor] | None = None
    tracking_range: tuple[float, float] | None = None
    noise_max: float = NOISE_MAX
    nominal: torch.Tensor | None = None  # the pipeline's nominal record (n_full,) [A], float64; None: unknown
    tracking_range_healthy: tuple[float, float] | None = None  # that of the healthy training records
    current_bound: float | None = None  # [A] the drive range the FDI was trained within (None: unchecked)
    shape_min: float = SHAPE_MIN  # the ``shape`` check's lowest correlation (metadata ``shape_correlation_min``)
    residual_floor: float | None = None  # [A] the ``unexplained`` check's r_0 (None: unchecked; diagnosis.contract_for)
    unexplained_ratio: float = UNEXPLAINED_RATIO  # its threshold (metadata ``unexplained_ratio_max``: never lower)
    spike_step: float = SPIKE_STEP  # the ``spikes`` check's step (metadata ``spike_step_max``: never lower)
    timing_ratio: float | None = None  # the ``timing`` check's (metadata ``timing_ratio_max``; None: not calibrated)

    @classmethod
    def of(
        cls, model: Any, metadata: Mapping[str, Any], command: Callable[[torch.Tensor], torch.Tensor] | None
    ) -> InputContract:
        """The contract of an exported pipeline from its metadata (:func:`~.export.read_metadata`)."""
        tracking, healthy = (_range(metadata, key) for key in ("tracking_nrmse", "tracking_nrmse_healthy"))
        levels = getattr(model, "interval_noise", None)
        noise_max = NOISE_MAX if levels is None or levels.numel() < 2 else NOISE_MARGIN * float(levels[-1])
        nominal = getattr(model, "nominal_record", None)
        usable = nominal is not None and bool(torch.isfinite(nominal).all()) and float(nominal.abs().max()) > 0
        bound, shape = metadata.get("drive_current_bound"), metadata.get("shape_correlation_min")
        ratio, step = metadata.get("unexplained_ratio_max"), metadata.get("spike_step_max")
        timing = metadata.get("timing_ratio_max")
        return cls(
            command,
            tracking,
            noise_max,
            nominal.double() if usable else None,
            healthy,
            None if bound is None else float(bound),
            SHAPE_MIN if shape is None else min(SHAPE_MIN, float(shape)),
            unexplained_ratio=UNEXPLAINED_RATIO if ratio is None else max(UNEXPLAINED_RATIO, float(ratio)),
            spike_step=SPIKE_STEP if step is None else max(SPIKE_STEP, float(step)),
            timing_ratio=None if timing is None else max(TIMING_RATIO, float(timing)),
        )

    def _tracking(self, record: Record, healthy: bool | None = None) -> dict[str, Any]:
        cmd, pos = record.command, record.position
        error = tracking_nrmse(cmd, pos)
        span = float(cmd.max() - cmd.min())
        gain = float(pos.max() - pos.min()) / span if span > 0 else math.nan
        corr = float(torch.corrcoef(torch.stack([pos.double().flatten(), cmd.double().flatten()]))[0, 1])
        known = (
            self.tracking_range_healthy if healthy and self.tracking_range_healthy is not None else self.tracking_range
        )
        if known is not None:
            low, high = known[0] / TRACKING_MARGIN, known[1] * TRACKING_MARGIN
            ok = low <= error <= high
        else:
            low, high = 0.0, TRACKING_NRMSE_MAX
            ok = error <= high and gain <= POSITION_GAIN
        ok = ok and not corr < REVERSED_CORRELATION  # NaN (a constant position) is not reversed
        return {"nrmse": error, "range": [low, high], "position_gain": gain, "correlation": corr, "ok": bool(ok)}

    def current_reasons(
        self,
        model: Any,
        current: torch.Tensor,
        noise: float,
        k_hat: torch.Tensor | None = None,
        measured: torch.Tensor | None = None,
        residual: float | None = None,
    ) -> list[str]:
        """The checks of the current (n_full,) [A] against the noise calibration and the nominal record, those
        of a near-nominal answer given its estimate k_hat (8,) (None: skipped); the run checks read ``measured``,
        the current as recorded (None: ``current``), so that the missing end of a record aligned on its trigger
        is no gap."""
        reasons = []
        if not math.isnan(noise) and noise > self.noise_max:
            reasons.append("noise")
        if not bool(within_drive_range(current.reshape(1, -1), self.current_bound)[0]):
            reasons.append("overcurrent")
        runs = current if measured is None else measured
        if runs.numel() == int(getattr(model, "n_full", runs.numel())):  # runs of a full record's samples
            reasons += run_reasons(runs)
        nominal, x = self.nominal, current.double()
        if nominal is None or nominal.shape != x.shape:
            return reasons
        scale = float(nominal.pow(2).mean().sqrt())
        mean = float(finite_mean(x))
        if mean * float(nominal.mean()) < 0:
            reasons.append("sign")
        large = large_faults(model, k_hat)
        if large is None:
            return reasons
        rms = float(finite_mean(x.pow(2)).sqrt())
        sigma = 0.0 if math.isnan(noise) else noise * rms  # noise std [A]
        if rest_offset(x, nominal, sigma, k_hat):
            reasons.append("offset")
        if large > 0:
            return reasons
        floor = self.residual_floor
        near = residual is not None and floor is not None and checked(k_hat, model.nominal, model.interval_mask)
        if near and unexplained_ratio(residual, noise, rms, floor) > self.unexplained_ratio:
            reasons.append("unexplained")
        if not bool(nominal_correlation(x, nominal) >= self.shape_min):
            reasons.append("shape")
        if has_spikes(x, sigma, max(scale, rms), self.spike_step):
            reasons.append("spikes")
        return reasons

    def check(
        self,
        model: Any,
        record: Record,
        current: torch.Tensor,
        noise: float,
        ood: bool,
        k_hat: torch.Tensor | None = None,
        healthy: bool | None = None,
        measured: torch.Tensor | None = None,
        residual: float | None = None,
    ) -> ContractChecks:
        """Every check of one record: ``current`` (n_full,) [A] as the pipeline saw it (after any rebase),
        ``noise`` its estimated relative noise (as measured), ``ood`` the pipeline's own flag, ``k_hat`` (8,) its
        estimate (None: the checks of a near-nominal answer are skipped), ``healthy`` its verdict (True: the
        position must follow the command as the healthy training records do, a dead or reversed sensor on a
        healthy actuator; None or False: as any training record does), ``measured`` the current as recorded
        (:meth:`current_reasons`), ``residual`` the pipeline's gappy residual [A] (the ``unexplained`` check)."""
        reasons, skipped, messages = [], [], []
        if ood:
            found = pipeline_reasons(model, current.unsqueeze(0))
            reasons += found[0] if found and found[0] else ["pipeline"]
        command = tracking = None
        # a column is checked on its finite samples (a record aligned on its trigger misses its ends)
        command_seen, position_seen = _present(record.command), _present(record.position)
        has_command, has_position = command_seen is not None, position_seen is not None
        if has_command and self.command is not None:
            n = min(record.command.numel(), current.numel())
            t = (record.time[:n] - record.time[0]).double()
            rate = sample_rate(record.time)
            seen = command_seen[:n]
            command = check_command(record.command[:n][seen], self.command(t)[seen], rate)
            if not command.ok:
                reasons.append("command")
                messages.append(command.reason())
        elif not has_command:
            skipped.append("command")
        both = command_seen & position_seen if has_command and has_position else None
        if both is not None and float(record.command[both].max() - record.command[both].min()) > 0:
            tracking = self._tracking(
                Record(record.time[both], record.command[both], record.position[both], record.current), healthy
            )
            if not tracking["ok"]:
                reasons.append("tracking")
                messages.append(
                    f"position does not follow the command as this actuator can: tracking NRMSE "
                    f"{tracking['nrmse']:.3f} outside [{tracking['range'][0]:.3f}, "
                    f"{tracking['range'][1]:.3f}], position range {tracking['position_gain']:.2f} "
                    f"x the command's, correlation {tracking['correlation']:.2f}{unit_hint('position', tracking['position_gain'])}"
                )
        else:  # no command or position column, or a constant command: nothing to follow
            skipped.append("tracking")
        reasons += [
            r for r in self.current_reasons(model, current, noise, k_hat, measured, residual) if r not in reasons
        ]
        if self.nominal is not None and rest_window(self.nominal) < REST_MIN:
            # a command that moves at once leaves no rest window: a probe offset is neither checked nor removed
            skipped.append("offset")
        return ContractChecks(reasons, skipped, command, tracking, messages)


def _present(x: torch.Tensor | None) -> torch.Tensor | None:
    """(n,) bool mask of the finite samples of a record's column; None where it is absent or less than
    ``MIN_PRESENT`` of it is finite."""
    if x is None:
        return None
    seen = torch.isfinite(x)
    return seen if float(seen.double().mean()) >= MIN_PRESENT else None
