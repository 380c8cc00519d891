"""Measurement model: the pipeline's k_hat and its calibrated error.

phm-evaluate calibrates, per difficulty class and noise level, the half-width w of a 90 % interval of the true
k around k_hat (``OnlinePipeline.k_interval``). The tracker reads k_hat = k + e with e of scale w / t_0.95(dof)
(``dof = inf``, the default: the Gaussian whose central 90 % is +/- w), in the Kalman filters of :mod:`.kalman`.
"""

from __future__ import annotations

import math

import torch
from scipy import stats

Z95 = 1.6448536269514722  # the standard normal's 95 % quantile
MIN_SCALE = 1e-4  # [k units]: a zero-width interval (a clamped bound) is not a perfect measurement


def t_quantile_95(dof: float) -> float:
    """The 95 % quantile of a Student-t with ``dof`` degrees of freedom (inf: the normal's)."""
    if not dof > 0:
        raise ValueError(f"measurement_dof must be > 0 (inf: Gaussian), got {dof!r}")
    return Z95 if math.isinf(dof) else float(stats.t.ppf(0.95, dof))


def interval_scale(k_hat: torch.Tensor, lower: torch.Tensor, upper: torch.Tensor, dof: float) -> torch.Tensor:
    """Error scale (B, 8) [k units] from the 90 % interval [lower, upper] (B, 8) around k_hat (B, 8).

    The interval is clamped to [0, 1], so the half-width is the larger of the two sides."""
    w = torch.maximum(upper - k_hat, k_hat - lower).to(torch.float64)
    return (w / t_quantile_95(dof)).clamp(min=MIN_SCALE)
