"""Sample-time selector interface: which ``n_points`` of the n_e samples of a signal to keep.

A selector sees the POD modes (n_e, n_m) and, when it uses them, the sample times (n_e,) [s]. After
``fit`` its ``indices_`` (n_points,) hold distinct sample indices in increasing (acquisition) order.
"""

from __future__ import annotations

import abc
from typing import ClassVar

import torch


def check_count(value: object, name: str, minimum: int = 1) -> int:
    """An int >= minimum from a constructor argument (no bools), else a ValueError naming ``name``."""
    if isinstance(value, bool) or not isinstance(value, int) or value < minimum:
        raise ValueError(f"{name} must be an integer >= {minimum}, got {value!r}")
    return value


class Selector(abc.ABC):
    """Base class: subclasses implement :meth:`_select` and set ``name``.

    Args:
        n_points: number of samples to keep, n_w (paper: 30).
    """

    name: ClassVar[str] = ""
    needs_snapshots: ClassVar[bool] = False  # True: fit(modes, time, snapshots=Y, mean=y0) (data-driven)

    def __init__(self, n_points: int):
        self.n_points = check_count(n_points, f"selector.n_points ({self.name})")

    def fit(self, modes: torch.Tensor, time: torch.Tensor | None = None) -> Selector:
        """Choose the samples from the POD modes (n_e, n_m); ``time`` (n_e,) [s] defaults to 0..n_e-1.

        Sets ``indices_`` (n_points,) int64, sorted increasing. Returns self.
        """
        if modes.ndim != 2:
            raise ValueError(f"modes must be (n_e, n_m), got shape {tuple(modes.shape)}")
        n_e = modes.shape[0]
        if not torch.isfinite(modes).all():
            raise ValueError("modes contain NaN or inf")
        if self.n_points > n_e:
            raise ValueError(f"selector.n_points={self.n_points} exceeds the {n_e} samples of a signal")
        if time is None:
            time = torch.arange(n_e, dtype=torch.float64)
        if time.shape != (n_e,):
            raise ValueError(f"time must have shape ({n_e},), got {tuple(time.shape)}")
        idx = self._select(modes.detach().to(torch.float64).cpu(), time.detach().to(torch.float64).cpu())
        idx = torch.as_tensor(idx, dtype=torch.long).flatten()
        if idx.numel() != self.n_points or idx.unique().numel() != self.n_points:
            raise RuntimeError(
                f"selector {self.name} returned {idx.numel()} indices "
                f"({idx.unique().numel()} distinct), expected {self.n_points}"
            )
        self.indices_ = torch.sort(idx).values
        return self

    @abc.abstractmethod
    def _select(self, modes: torch.Tensor, time: torch.Tensor) -> torch.Tensor:
        """Indices (n_points,) of distinct samples, any order; ``modes`` (n_e, n_m) and ``time`` float64."""

    def get_params(self) -> dict[str, object]:
        """Constructor arguments (sklearn style), for the bundle and reports."""
        return {"n_points": self.n_points}

    def __repr__(self) -> str:
        args = ", ".join(f"{k}={v!r}" for k, v in self.get_params().items())
        return f"{type(self).__name__}({args})"
