"""Resampling of equally-many particles per actuator, batched: systematic resampling, then a Liu-West kernel
step so that repeated resampling does not collapse the cloud onto a few copies.

Liu & West (2001): each resampled particle x moves to a x + (1 - a) mean + h L z with h^2 = 1 - a^2 and L the
Cholesky factor of the cloud's covariance; the cloud keeps its mean and covariance (a^2 + h^2 = 1) while its
copies spread out. It matters for the static wear-rate scale s, which has no process noise of its own.
"""

from __future__ import annotations

import torch

JITTER = 1e-12  # added to the covariance's diagonal: a component every particle agrees on (a clamped 0)


def systematic_indices(log_w: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
    """Systematic resampling: log weights (B, P) and one uniform u (B,) in [0, 1) per row -> ancestor
    indices (B, P), each particle i drawn floor(P w_i) or ceil(P w_i) times."""
    w = torch.softmax(log_w, dim=-1)
    p = w.shape[-1]
    cdf = w.cumsum(-1)
    cdf[:, -1] = 1.0  # rounding: the last edge closes the interval
    positions = (u.unsqueeze(-1) + torch.arange(p, dtype=w.dtype, device=w.device)) / p
    return torch.searchsorted(cdf, positions.contiguous()).clamp(max=p - 1)


def liu_west(x: torch.Tensor, z: torch.Tensor, shrink: float) -> torch.Tensor:
    """Kernel step of equally weighted particles x (B, P, d) with standard normals z (B, P, d); ``shrink`` = a
    in (0, 1] (1: no move). Returns (B, P, d) with the same mean and covariance per row."""
    if shrink >= 1.0:
        return x
    mean = x.mean(1, keepdim=True)
    dev = x - mean
    cov = dev.transpose(1, 2) @ dev / x.shape[1]
    eye = torch.eye(x.shape[-1], dtype=x.dtype, device=x.device)
    chol, info = torch.linalg.cholesky_ex(cov + JITTER * eye)
    if bool((info > 0).any()):  # a degenerate cloud: its own spread per component
        diag = torch.diag_embed(cov.diagonal(dim1=1, dim2=2).clamp(min=0).sqrt())
        chol = torch.where((info > 0).view(-1, 1, 1), diag, chol)
    h = (1.0 - shrink * shrink) ** 0.5
    return shrink * x + (1.0 - shrink) * mean + h * z @ chol.transpose(1, 2)
