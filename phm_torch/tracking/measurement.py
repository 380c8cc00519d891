"""Measurement model: the pipeline's k_hat and its calibrated error.

phm-evaluate calibrates, per difficulty class and noise level, the half-width w of a 90 % interval of the true
k around k_hat (``OnlinePipeline.k_interval``). The tracker reads k_hat = k + e with e a Student-t of ``dof``
degrees of freedom (a Gaussian for ``dof = inf``) whose central 90 % is +/- w: scale = w / t_0.95(dof). The
heavy tail keeps one wrong estimate (an ambiguous fault pattern the FDI maps to another component) from
wiping out the particles that explain the other inspections.
"""

from __future__ import annotations

import math

import torch
from scipy import stats

Z95 = 1.6448536269514722      # the standard normal's 95 % quantile
MIN_SCALE = 1e-4               # [k units]: a zero-width interval (a clamped bound) is not a perfect measurement


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


def log_likelihood(k: torch.Tensor, k_hat: torch.Tensor, scale: torch.Tensor, dof: float) -> torch.Tensor:
    """log p(k_hat | k) (B, P) up to a constant per row, components independent: particles k (B, P, 8),
    estimates k_hat (B, 8), scales (B, 8).

    The pipeline's k_hat is clamped to [0, 1]: an estimate at a bound says only that k + e fell beyond it, so
    there the likelihood is the tail probability (a censored, Tobit reading; Gaussian tail). Read as a
    point, a zero estimate of an undamaged component would pull the particles up to the noise's mean
    positive part, and the law would then grow that phantom damage and bias s low."""
    k_hat, scale = k_hat.unsqueeze(1).to(k), scale.unsqueeze(1).to(k)
    z = (k_hat - k) / scale
    point = -0.5 * z * z if math.isinf(dof) else -0.5 * (dof + 1.0) * torch.log1p(z * z / dof)
    low, high = k_hat <= BOUND, k_hat >= 1.0 - BOUND
    tail = torch.special.log_ndtr(torch.where(high, -z, z))      # P(e <= -k) at 0, P(e >= 1 - k) at 1
    # per row and component, either the point density or the tail applies to every particle: their different
    # normalisations are constants of the row and cancel in the weights
    return torch.where(low | high, tail, point).sum(-1)


BOUND = 1e-9       # an estimate within this of 0 or 1 sits at the clamp
