"""Thresholds of the out-of-distribution checks: quantiles over the training records with measurement noise.

Clean simulated records alone can lie so close to the POD span (few modes, an LF store) that any real
measurement would be flagged, so each threshold is a quantile over the training records *with the rated
measurement noise* added. The records are corrupted and checked in row blocks: a noisy copy of an
80,000-record store would take 3.2 GB, its noise another 3.2 GB.
"""

from __future__ import annotations

import torch

from .augment import add_noise, rms
from .full_signal_check import FullSignalCheck
from .gappy_pod import GappyPOD

# the most the roughness threshold is raised to: white noise (sqrt 2) stays above it whatever the sampling
ROUGHNESS_MAX = 1.3


def ood_thresholds(
    signals: torch.Tensor,
    gappy: GappyPOD,
    check: FullSignalCheck,
    noise: float,
    quantile: float,
    seed: int,
    block_rows: int = 2048,
) -> tuple[float, float]:
    """Gappy-residual and full-record-residual thresholds.

    Args:
        signals: (n, n_e) training records [A].
        gappy: the fitted gappy layer.   check: the full-record check (its residual is used).
        noise: relative std of the added white noise (fraction of each record's RMS current).
        quantile: the quantile taken, in [0, 1].
        seed: seed of the noise (one generator over the blocks in order).
        block_rows: records corrupted at a time.

    Returns:
        (gappy residual threshold [A], full-record POD residual threshold [fraction]).
    """
    if not 0.0 <= quantile <= 1.0:
        raise ValueError(f"eval.ood_quantile must be in [0, 1], got {quantile!r}")
    generator = torch.Generator().manual_seed(seed)
    gappy_resid, full_resid = [], []
    with torch.no_grad():
        for start in range(0, signals.shape[0], block_rows):
            block = signals[start : start + block_rows]
            noisy = add_noise(block, rms(block), noise, generator)
            gappy_resid.append(gappy(gappy.select(noisy))[1].to(torch.float64))
            full_resid.append(check.residual(noisy).to(torch.float64))
    return (
        float(torch.quantile(torch.cat(gappy_resid), quantile)),
        float(torch.quantile(torch.cat(full_resid), quantile)),
    )


def shape_thresholds(
    signals: torch.Tensor, check: FullSignalCheck, quantile: float, margin: float = 1.5, block_rows: int = 8192
) -> tuple[float, float]:
    """The roughness and plateau thresholds of a trained pipeline: each the check's own (a physical default)
    unless the clean training records reach ``quantile`` of it, then ``margin`` times their quantile.

    Both statistics depend on the sampling as much as on the signal: the roughness of a smooth record grows as
    the sample rate falls (the reference's heaviest fault: 0.25 at 20 kHz, 0.76 at 5 kHz), and a test command
    that ends on a slow crest puts several sampled points within the plateau's tolerance of the maximum (a
    0-10 Hz chirp at 10 kHz: 9 % of the clean training records above 0.5 %). Clean records, not noisy ones:
    noise breaks a smooth crest into separate samples but leaves a clipped record's flat top flat, and a
    record rougher than the clean training set's roughest by half again is noise-dominated whatever its rate.

    Args:
        signals: (n, n_e) training records [A].   check: the full-record check (its shape statistics).
        quantile: the quantile taken, in [0, 1] (``eval.ood_quantile``).
        margin: factor above the training quantile (>= 1; 1.5: one sampled point more than the training set's
            worst lies within the plateau on a ~300-point record).
        block_rows: records checked at a time.

    Returns:
        (roughness threshold (at most ``ROUGHNESS_MAX`` when raised), plateau threshold).
    """
    if not 0.0 <= quantile <= 1.0:
        raise ValueError(f"eval.ood_quantile must be in [0, 1], got {quantile!r}")
    if not margin >= 1.0:
        raise ValueError(f"shape threshold margin must be >= 1, got {margin!r}")
    rough, plateau = [], []
    with torch.no_grad():
        for start in range(0, signals.shape[0], block_rows):
            _, r, p = check.statistics(signals[start : start + block_rows])
            rough.append(r.to(torch.float64))
            plateau.append(p.to(torch.float64))
    out = []
    for values, default in ((rough, check.roughness_threshold), (plateau, check.plateau_threshold)):
        v = torch.cat(values) if values else torch.empty(0, dtype=torch.float64)
        v = v[torch.isfinite(v)]  # a flat record has no roughness
        out.append(default if v.numel() == 0 else max(default, margin * float(torch.quantile(v, quantile))))
    return max(check.roughness_threshold, min(out[0], ROUGHNESS_MAX)), out[1]
