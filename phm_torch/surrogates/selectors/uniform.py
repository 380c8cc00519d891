"""Evenly spaced samples (the baseline every informed selector must beat)."""

from __future__ import annotations

import torch

from .base import Selector


class UniformSelector(Selector):
    """``n_points`` samples evenly spaced over the record, first and last included (one point: the middle).

    Args:
        n_points: number of samples to keep.
    """

    name = "uniform"

    def _select(self, modes: torch.Tensor, time: torch.Tensor) -> torch.Tensor:
        n_e = modes.shape[0]
        if self.n_points == 1:
            return torch.tensor([n_e // 2])
        # Spacing (n_e - 1) / (n_points - 1) >= 1 when n_points <= n_e, so rounding keeps them distinct.
        return torch.linspace(0, n_e - 1, self.n_points, dtype=torch.float64).round().long()
