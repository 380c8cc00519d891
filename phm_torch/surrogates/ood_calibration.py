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


def plateau_threshold(
    signals: torch.Tensor, check: FullSignalCheck, quantile: float, margin: float = 1.5, block_rows: int = 8192
) -> float:
    """The plateau threshold of a trained pipeline: the check's own (physical default) unless the clean training
    records reach ``quantile`` of it, then ``margin`` times their quantile.

    Clean records, not noisy ones: noise breaks a smooth crest into separate samples (a lower plateau) but
    leaves a clipped record's flat top flat, so the clean records bound what a valid record can reach.

    Args:
        signals: (n, n_e) training records [A].   check: the full-record check (its plateau statistic).
        quantile: the quantile taken, in [0, 1] (``eval.ood_quantile``).
        margin: factor above the training quantile (> 1: one sampled point more than the training set's
            worst lies within it on a ~300-point record).
        block_rows: records checked at a time.
    """
    if not 0.0 <= quantile <= 1.0:
        raise ValueError(f"eval.ood_quantile must be in [0, 1], got {quantile!r}")
    if not margin >= 1.0:
        raise ValueError(f"plateau margin must be >= 1, got {margin!r}")
    with torch.no_grad():
        blocks = [check.plateau(signals[i : i + block_rows]) for i in range(0, signals.shape[0], block_rows)]
    plateau = torch.cat(blocks).to(torch.float64) if blocks else torch.empty(0)
    if plateau.numel() == 0:
        return check.plateau_threshold
    return max(check.plateau_threshold, margin * float(torch.quantile(plateau, quantile)))
