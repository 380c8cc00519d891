"""The calibration steps of the evaluation pipeline: what phm-evaluate fits on the held-out split so that the
exported pipeline's uncertainty (RUL band, P(faulty), k_hat intervals) is honest, and the input contract's
tracking ranges."""

from __future__ import annotations

import logging
from collections.abc import Sequence

import torch

from ...data.store import DatasetStore
from ...faults import FAULT_NAMES
from ...online import OnlinePipeline
from ...online.fdi_band import FDIBand, TooFewCalibrationSignals, calibrate_fdi_band
from ...online.fdi_interval import FDIInterval, calibrate_fdi_interval
from ...online.input_contract import tracking_range
from ...online.verdict import calibrate_verdict, shift_prior
from ...surrogates.augment import add_noise, rms
from ...surrogates.metrics import IDENTIFIED_R2, fdi_identifiability
from .settings import CalibrationSettings

log = logging.getLogger(__name__)


def noisy(signals: torch.Tensor, noise: float, seed: int) -> torch.Tensor:
    """The held-out calibration signals with ``fdi_band.noise`` relative measurement noise."""
    if noise > 0 and signals.shape[0]:
        signals = add_noise(signals, rms(signals), noise, torch.Generator().manual_seed(seed + 2))
    return signals


def fdi_band(pipeline: OnlinePipeline, signals: torch.Tensor, k: torch.Tensor, correct_median: bool) -> FDIBand | None:
    """The FDI band calibrated on held-out (noisy) signals, or None (with a warning: the full-flow band is
    then the physics band only, too narrow) when too few are usable."""
    try:
        return calibrate_fdi_band(pipeline, signals, k, correct_median=correct_median)
    except TooFewCalibrationSignals as err:
        log.warning("%s; the full-flow RUL band holds the physics spread only", err)
        return None


def verdict_scaling(
    prior: float | None, score: torch.Tensor, ood: torch.Tensor, healthy: torch.Tensor
) -> tuple[float, float, float] | None:
    """Platt scaling (a, b) of the pipeline's health score on held-out (noisy) signals, moved to the fault
    rate ``prior`` (None: the signals' own), and that rate; or None (with a warning: the exported
    pipeline's P(faulty) is then NaN) when the signals are not two-class. ``score`` and ``ood`` (N,): the
    pipeline's outputs on them."""
    keep = ~ood & torch.isfinite(score)
    try:
        a, b = calibrate_verdict(score[keep], ~healthy[keep])
    except ValueError as err:
        log.warning("verdict not calibrated: %s", err)
        return None
    own = float((~healthy[keep]).double().mean())
    if prior is None:
        return a, b, own
    return a, shift_prior(b, own, prior), prior


def identifiability(k_hat: torch.Tensor, k: torch.Tensor, ood: torch.Tensor) -> dict[str, float]:
    """R^2 of each component's estimate on the in-distribution calibration records {fault name: R^2}
    (:func:`~phm_torch.surrogates.metrics.fdi_identifiability`); a warning names those the test command does not
    identify, whose k_hat is mostly the training prior."""
    keep = ~ood
    r2 = (
        fdi_identifiability(k_hat[keep].to(torch.float64), k[keep].to(torch.float64))
        if int(keep.sum()) > 1
        else [float("nan")] * len(FAULT_NAMES)
    )
    out = {name: round(v, 4) for name, v in zip(FAULT_NAMES, r2)}
    weak = {name: v for name, v in out.items() if not v >= IDENTIFIED_R2}
    if weak:
        log.warning(
            "this pipeline does not identify %s (R^2 %s on held-out records, below %.2f): their k_hat is "
            "mostly the training prior; phm-predict lists them under k_not_identified. Whether the records carry "
            "them (more modes and a wider FDI would read them) or the test command does not excite them: "
            "scripts/fdi_capacity_probe.py",
            ", ".join(weak),
            ", ".join(f"{v:.2f}" for v in weak.values()),
            IDENTIFIED_R2,
        )
    return out


def _fdi_interval(
    settings: CalibrationSettings,
    nominal: torch.Tensor,
    k_hat: torch.Tensor,
    ood: torch.Tensor,
    k: torch.Tensor,
) -> FDIInterval | None:
    """Conformal half-widths of the k_hat intervals from the pipeline's estimates k_hat (N, 8) and flags ood
    (N,) on held-out (noisy) signals of true fault vectors k (N, 8), or None (with a warning: the exported
    pipeline's intervals are then NaN) when too few are in distribution."""
    coverage, min_count = settings.coverage, settings.min_count
    if int((~ood).sum()) < min_count:
        log.warning(
            "k_hat intervals not calibrated: %d in-distribution records, fdi_interval.min_count=%d",
            int((~ood).sum()),
            min_count,
        )
        return None
    return calibrate_fdi_interval(k_hat[~ood], k[~ood].to(k_hat.dtype), nominal, coverage, min_count)


def fdi_intervals(
    settings: CalibrationSettings,
    pipeline: OnlinePipeline,
    k_hat: torch.Tensor,
    ood: torch.Tensor,
    clean: torch.Tensor,
    k: torch.Tensor,
    seed: int,
    unidentified: Sequence[int] = (),
) -> tuple[FDIInterval | None, list[float]]:
    """Calibrate the pipeline's k_hat intervals in place at every noise level of ``settings``: the first from
    the pipeline's outputs k_hat, ood on the (noisy) calibration signals, the others from the noise-free
    ``clean`` signals (N, n) with that level of noise added. Returns the first level's interval (None: not
    calibrated) and the levels calibrated.

    The components of ``unidentified`` (the test command does not identify them) get the whole range [0, 1]: their
    k_hat is mostly the training prior, so a conformal width holds only for the calibration split's own spread of
    them. The 270 V rudder's eccentricity (R^2 0.13) had a width calibrated on a store of heavy faults; on clean
    near-nominal records its interval held the truth 27 % of the time."""
    interval = _fdi_interval(settings, pipeline.nominal, k_hat, ood, k)
    if interval is not None and unidentified:
        interval.half_widths[:, list(unidentified)] = 1.0
    levels = list(settings.noise_levels[:1])
    if interval is None:
        return None, levels
    widths = [interval.half_widths]
    for i, level in enumerate(settings.noise_levels[1:]):
        noisy = add_noise(clean, rms(clean), level, torch.Generator().manual_seed(seed + 10 + i))
        with torch.no_grad():
            k_hat_l, _, _, ood_l, _ = pipeline(noisy.to(pipeline.times.dtype))
        more = _fdi_interval(settings, pipeline.nominal, k_hat_l, ood_l, k)
        if more is None:
            break
        widths.append(torch.maximum(more.half_widths, widths[-1]))  # never narrower with more noise
        levels.append(level)
    pipeline.k_half_widths = torch.stack(widths).to(pipeline.times.dtype)
    pipeline.interval_noise = torch.tensor(levels, dtype=pipeline.times.dtype)
    pipeline.interval_level = interval.level
    return interval, levels


def tracking_ranges(store: DatasetStore, block_rows: int = 2048) -> tuple[list[float], list[float] | None]:
    """The tracking NRMSE range over every split with positions (train, val, rul; read in row blocks), and that of
    its healthy records: the input contract's position check (phm-predict). Every split, not the evaluated one
    alone: the rul split's 100 vectors spanned 0.109-0.118 on the paper store, a clean double short of the val
    design reads 0.19, and a motor with every phase shorted does not move at all (train: 0.08-0.49). The
    healthy range (0.08-0.19 there) is the one a record the pipeline calls healthy must meet: a dead or
    reversed position sensor on a healthy actuator is caught, on a faulty one it can be the fault itself."""
    command = torch.as_tensor(store.command)
    ranges: dict[bool, list[float]] = {}
    for name in store.splits:
        view = store.split(name)
        if "position" not in view.group or len(view) == 0:
            continue
        for start in range(0, len(view), block_rows):
            position = torch.as_tensor(view.position[start : start + block_rows])
            healthy = torch.as_tensor(view.healthy[start : start + block_rows]).bool()
            for key, rows in ((False, position), (True, position[healthy])):
                if rows.shape[0]:
                    lo, hi = tracking_range(command, rows)
                    old = ranges.get(key, [lo, hi])
                    ranges[key] = [min(old[0], lo), max(old[1], hi)]
    if False not in ranges:
        raise ValueError(f"store {store.data_dir}: no split holds positions (the input contract's tracking check)")
    return ranges[False], ranges.get(True)
