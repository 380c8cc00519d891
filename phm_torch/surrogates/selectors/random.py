"""Random samples without replacement (a seeded control for the ablations)."""

from __future__ import annotations

import torch

from .base import Selector, check_count


class RandomSelector(Selector):
    """``n_points`` distinct samples drawn uniformly at random.

    Args:
        n_points: number of samples to keep.
        seed: seed of the ``torch.Generator`` (same seed, same samples).
    """

    name = "random"

    def __init__(self, n_points: int, seed: int = 0):
        super().__init__(n_points)
        self.seed = check_count(seed, "selector.seed", 0)

    def _select(self, modes: torch.Tensor, time: torch.Tensor) -> torch.Tensor:
        gen = torch.Generator().manual_seed(self.seed)
        return torch.randperm(modes.shape[0], generator=gen)[: self.n_points]

    def get_params(self) -> dict[str, object]:
        return {**super().get_params(), "seed": self.seed}
