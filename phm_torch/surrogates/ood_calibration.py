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
