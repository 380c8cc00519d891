"""Out-of-distribution check on a full record: the share of its energy that the POD basis cannot explain.

With n_points close to n_modes (the paper: 30 and 22) the gappy residual has few degrees of freedom and
heavy-fault training records (ringing phase currents, several amperes of residual) overlap garbage.
A full record says much more: the relative residual of its projection on the POD modes,

    r(y) = || d - P P^T d || / || d ||,   d = y - mean,

is ~1 for noise or any foreign waveform and below ~0.9 for every training record. It is computed on
every ``stride``-th sample (default 16: 626 of 10001, ~5 us per record in a batch; white noise still
scores ~sqrt(1 - n_m / 626) ~ 0.98) with an orthonormalised basis of those rows, so that one
(B, n_e / stride) x (n_e / stride, n_m) product gives ||d||^2 - ||Q^T d||^2.
"""

from __future__ import annotations

import torch
from torch import nn


class FullSignalCheck(nn.Module):
    """Relative POD residual of full records.

    Args:
        modes: POD modes (n_e, n_m).   mean: mean record (n_e,) [A].
        stride: use every ``stride``-th sample (>= 1).
    """

    def __init__(self, modes: torch.Tensor, mean: torch.Tensor, stride: int = 16):
        super().__init__()
        if isinstance(stride, bool) or not isinstance(stride, int) or stride < 1:
            raise ValueError(f"full_signal_check.stride must be an integer >= 1, got {stride!r}")
        if modes.dim() != 2 or mean.shape != modes.shape[:1]:
            raise ValueError(f"modes (n_e, n_m) and mean (n_e,) expected, got {tuple(modes.shape)} and "
                             f"{tuple(mean.shape)}")
        rows = torch.arange(0, modes.shape[0], stride)
        q, _ = torch.linalg.qr(modes[rows].to(torch.float64))
        self.register_buffer("rows", rows)
        self.register_buffer("basis", q.to(modes.dtype))                 # (n_e / stride, n_m), orthonormal
        self.register_buffer("mean_rows", mean[rows].to(modes.dtype))
        self.n_full = int(modes.shape[0])

    def forward(self, signals: torch.Tensor) -> torch.Tensor:
        """r (B,) in [0, 1] of full records (B, n_e) [A]; NaN where a used sample is not finite."""
        if signals.dim() != 2 or signals.shape[1] != self.n_full:
            raise ValueError(f"full_signal_check: records must be (B, {self.n_full})")
        d = signals.index_select(1, self.rows).to(self.basis.dtype) - self.mean_rows
        energy = d.pow(2).sum(1)
        explained = (d @ self.basis).pow(2).sum(1)
        return ((energy - explained).clamp(min=0.0) / energy.clamp(min=1e-30)).sqrt()
