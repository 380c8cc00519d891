"""An out-of-distribution threshold that follows the record's measurement noise.

The gappy residual of a record grows with its white noise (the noise's RMS over the selected samples, less
the part the modes absorb), so a single threshold calibrated at one noise level rejects clean but noisier
records: the shipped pipeline's threshold, the 99.9 % quantile of the training records at 1 % noise, flagged
1.6 % of clean val-like records at 0-3 % noise, all of them noisy records of heavy faults. phm-evaluate
calibrates the threshold per noise level on held-out records (:func:`calibrate_gappy_residual`), never below
the training threshold, and the pipeline interpolates it at each record's estimated noise, as the consistency
check and the k_hat intervals do.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Sequence

import torch
from torch import nn

from ..surrogates.augment import add_noise, rms


class NoiseScaledThreshold(nn.Module):
    """Threshold (B,) at relative noise levels (B,), linear between calibrated levels, held beyond them.

    Args:
        values: (n_levels,) thresholds > 0 (any unit: that of the statistic compared).
        levels: (n_levels,) increasing relative noise levels (noise std / record RMS); None: one level, 0.
    """

    def __init__(
        self,
        values: torch.Tensor | Sequence[float] | float,
        levels: torch.Tensor | Sequence[float] | None = None,
        dtype: torch.dtype = torch.float32,
    ):
        super().__init__()
        self.dtype = dtype
        self.set(values, levels)

    def set(
        self, values: torch.Tensor | Sequence[float] | float, levels: torch.Tensor | Sequence[float] | None = None
    ) -> None:
        """Replace the thresholds ``values`` (n_levels,) at ``levels`` (n_levels,) (None: one level, 0)."""
        v = torch.as_tensor(values, dtype=self.dtype).reshape(-1)
        lv = (
            torch.zeros(v.numel(), dtype=self.dtype)
            if levels is None
            else torch.as_tensor(levels, dtype=self.dtype).reshape(-1)
        )
        if v.numel() < 1 or lv.numel() != v.numel() or bool((lv[1:] <= lv[:-1]).any()) or not bool((v > 0).all()):
            raise ValueError(
                f"noise-scaled threshold: values must be > 0, one per increasing noise level, got "
                f"{v.tolist()} at {lv.tolist()}"
            )
        self.register_buffer("values", v.contiguous())
        self.register_buffer("levels", lv.contiguous())

    def forward(self, noise: torch.Tensor) -> torch.Tensor:
        return interpolate_levels(self.levels, self.values, noise)


def interpolate_levels(levels: torch.Tensor, values: torch.Tensor, noise: torch.Tensor) -> torch.Tensor:
    """values (n_levels,) calibrated at increasing noise ``levels`` (n_levels,), interpolated linearly at
    ``noise`` (B,) and held beyond the first and last level -> (B,)."""
    n = levels.shape[0]
    if n == 1:
        return values[0].expand(noise.shape[0])
    x = torch.minimum(torch.maximum(noise.to(levels.dtype), levels[0]), levels[-1])
    low = (torch.searchsorted(levels, x, right=True) - 1).clamp(0, n - 2)
    frac = (x - levels[low]) / (levels[low + 1] - levels[low])
    return values[low] * (1.0 - frac) + values[low + 1] * frac


def conformal_quantile(values: torch.Tensor, quantile: float) -> float:
    """The split-conformal ``quantile`` of finite ``values`` (N,): the ceil((N + 1) q)-th smallest (the largest
    when N is too small for q)."""
    v = values[torch.isfinite(values)].to(torch.float64).sort().values
    if v.numel() == 0:
        raise ValueError("conformal_quantile: no finite value")
    return float(v[min(v.numel(), math.ceil((v.numel() + 1) * quantile)) - 1])


@torch.no_grad()
def calibrate_gappy_residual(
    pipeline: nn.Module,
    clean: torch.Tensor,
    levels: Sequence[float],
    seed: int,
    quantile: float,
    block_rows: int = 1024,
) -> dict[str, list[float] | float]:
    """Set the pipeline's gappy-residual threshold per noise level, in place, on held-out records.

    Args:
        pipeline: an :class:`~phm_torch.online.OnlinePipeline`.
        clean: (N, n_full) noise-free held-out records [A] (phm-evaluate's fdi_band split).
        levels: increasing relative noise levels; white noise of each level is added to the records.
        seed: seeds the noise.   quantile: the split-conformal quantile of the residual taken at each level.

    Each threshold is at least the training threshold (``pipeline.residual_threshold``), so the calibration
    never flags more records than the training threshold alone. Returns ``{"thresholds", "noise_levels",
    "quantile"}`` [A] (rul_calibration.json's ``gappy_residual``; phm-export passes it back).
    """
    if not 0.0 < quantile < 1.0:
        raise ValueError(f"ood.quantile must be in (0, 1), got {quantile!r}")
    if not levels or any(b <= a for a, b in itertools.pairwise(levels)):
        raise ValueError(f"gappy residual calibration: noise levels must be increasing, got {list(levels)}")
    floor = float(pipeline.residual_threshold)
    thresholds = []
    for i, level in enumerate(levels):
        noisy = (
            add_noise(clean, rms(clean), level, torch.Generator().manual_seed(seed + 40 + i)) if level > 0 else clean
        )
        residual = torch.cat(
            [
                pipeline.gappy(pipeline.gappy.select(block.to(pipeline.times.dtype)))[1]
                for block in noisy.split(block_rows)
            ]
        )
        thresholds.append(max(floor, conformal_quantile(residual, quantile)))
    pipeline.residual_limit.set(thresholds, levels)
    return {"thresholds": thresholds, "noise_levels": [float(v) for v in levels], "quantile": float(quantile)}
