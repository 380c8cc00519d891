"""Self-organising map selector (the seed paper's second compression step).

The SOM is trained on the rows of T = [t, v_1, ..., v_nm] (n_e, n_m + 1): one point per sample, its
time and the values of the first n_m POD modes there. Its n_w neurons settle along this curve, denser
where the modes vary fast; the time component of each neuron's weight vector is a selected time
(paper: "the first components of all the n_w weight vectors encode the most informative
time-locations"), rounded here to the nearest free sample.

Training is the batch SOM (Kohonen's batch map, MATLAB ``selforgmap``'s default ``trainbu``): every
epoch assigns every row to its best-matching neuron (L2) and moves each neuron to the
neighbourhood-weighted mean of the rows, with a Gaussian neighbourhood on the map grid whose width
shrinks geometrically from ``sigma_start`` to ``sigma_end``. It is deterministic and independent of
the presentation order.

The map places its neurons where the modes vary, not where they are independent: on another actuator's modes its
30 points can leave the gappy matrix G = V[S]^T V[S] nearly singular (measured on a flap EMA's 10,000-signal
store: condition number 8,259 and err_alpha 23 %, where the reference actuator's selections stay at 61-306). Above
``max_condition`` the selector exchanges the fewest of its points that bring it within the bound
(:func:`~.exchange.exchange_points`: two there, 535 and 8.6 %), keeping the rest of the map's placement; the
greedy E-optimal set (:class:`GreedySelector`) only where the exchange cannot reach the bound. It says so in the log
and in ``fallback_``.

Column scaling: with ``column_scaling="maxabs"`` the time column is mapped to [0, 1] and each mode is
divided by its largest magnitude, then the time column is multiplied by ``time_weight``. Unscaled
(``"none"``), t in seconds dominates the unit-norm modes (entries ~ n_e^-1/2) and the map degenerates
towards uniform sampling.
"""

from __future__ import annotations

import logging
import math

import torch

from .base import Selector, check_count
from .exchange import exchange_points, gram_condition
from .greedy import GreedySelector

log = logging.getLogger(__name__)

SCALINGS = ("maxabs", "none")


class SOMSelector(Selector):
    """Batch self-organising map on [t, v_1..v_nm]; neuron times are the selected samples.

    Args:
        n_points: number of neurons = samples kept (paper: 30).
        map_shape: grid (rows, cols) of the map with rows * cols = n_points; ``None`` = a chain
            (1, n_points), which suits data lying on a curve.
        time_weight: factor on the scaled time column (larger: more even spread in time).
        column_scaling: ``maxabs`` or ``none`` (see the module note).
        epochs: batch-SOM epochs.
        sigma_start: initial neighbourhood width [grid units]; ``None`` = max(rows, cols) / 4 (>= 1).
        sigma_end: final neighbourhood width [grid units].
        max_condition: largest condition number of the gappy matrix V[S]^T V[S] the map's points may leave;
            above it the fewest points are exchanged that bring it within (needs n_points > n_m). None: the
            map's points always.

    Fitted: ``indices_``; ``weights_`` (n_points, n_m + 1) the map; ``condition_`` the kept points' condition
    number; ``fallback_`` None, or {replaced (how many of the map's points were exchanged), som_condition, condition}.
    """

    name = "som"

    def __init__(
        self,
        n_points: int,
        map_shape: tuple[int, int] | list[int] | None = None,
        time_weight: float = 1.0,
        column_scaling: str = "maxabs",
        epochs: int = 100,
        sigma_start: float | None = None,
        sigma_end: float = 0.5,
        max_condition: float | None = 1000.0,
    ):
        super().__init__(n_points)
        if map_shape is None:
            map_shape = (1, n_points)
        shape = tuple(map_shape)
        if len(shape) != 2 or any(isinstance(s, bool) or not isinstance(s, int) or s < 1 for s in shape):
            raise ValueError(f"selector.map_shape must be two positive integers (rows, cols), got {map_shape!r}")
        if shape[0] * shape[1] != n_points:
            raise ValueError(
                f"selector.map_shape {list(shape)} has {shape[0] * shape[1]} neurons but "
                f"n_points={n_points}: rows * cols must equal n_points"
            )
        if not (isinstance(time_weight, (int, float)) and math.isfinite(time_weight) and time_weight > 0):
            raise ValueError(f"selector.time_weight must be a positive number, got {time_weight!r}")
        if column_scaling not in SCALINGS:
            raise ValueError(f"selector.column_scaling must be one of {list(SCALINGS)}, got {column_scaling!r}")
        sigma0 = max(max(shape) / 4.0, 1.0) if sigma_start is None else sigma_start
        if not (
            isinstance(sigma0, (int, float))
            and isinstance(sigma_end, (int, float))
            and 0 < sigma_end <= sigma0
            and math.isfinite(sigma0)
        ):
            raise ValueError(
                f"selector.sigma_start and sigma_end must satisfy 0 < sigma_end <= sigma_start, "
                f"got sigma_start={sigma_start!r}, sigma_end={sigma_end!r}"
            )
        if max_condition is not None and not (
            isinstance(max_condition, (int, float)) and not isinstance(max_condition, bool) and max_condition >= 1
        ):
            raise ValueError(f"selector.max_condition must be a number >= 1 or null, got {max_condition!r}")
        self.max_condition = None if max_condition is None else float(max_condition)
        self.map_shape = shape
        self.time_weight = float(time_weight)
        self.column_scaling = column_scaling
        self.epochs = check_count(epochs, "selector.epochs")
        self.sigma_start = sigma_start
        self.sigma_end = float(sigma_end)
        self._sigma0 = float(sigma0)

    def training_data(self, modes: torch.Tensor, time: torch.Tensor) -> torch.Tensor:
        """The scaled SOM training set T (n_e, n_m + 1), time first."""
        t = time.unsqueeze(-1)
        if self.column_scaling == "maxabs":
            span = (time.max() - time.min()).clamp(min=torch.finfo(time.dtype).tiny)
            t = (t - time.min()) / span
            modes = modes / modes.abs().amax(0).clamp(min=torch.finfo(modes.dtype).tiny)
        return torch.cat([t * self.time_weight, modes], dim=1)

    def train_map(self, data: torch.Tensor) -> torch.Tensor:
        """Batch-SOM weights (n_points, d) trained on ``data`` (n_e, d)."""
        rows, cols = self.map_shape
        grid = torch.stack(
            torch.meshgrid(torch.arange(rows, dtype=data.dtype), torch.arange(cols, dtype=data.dtype), indexing="ij"),
            -1,
        ).reshape(-1, 2)
        grid_d2 = torch.cdist(grid, grid).pow(2)  # (n_w, n_w) squared map distances
        # Initial neurons: the rows at evenly spaced samples, in map (row-major) order.
        start = torch.linspace(0, data.shape[0] - 1, self.n_points, dtype=torch.float64).round().long()
        weights = data[start].clone()
        ratio = self.sigma_end / self._sigma0
        for epoch in range(self.epochs):
            sigma = self._sigma0 * ratio ** (epoch / max(self.epochs - 1, 1))
            bmu = torch.cdist(data, weights).argmin(1)  # (n_e,) best-matching neuron
            counts = torch.bincount(bmu, minlength=self.n_points).to(data.dtype)
            sums = torch.zeros_like(weights).index_add_(0, bmu, data)
            h = torch.exp(-grid_d2 / (2.0 * sigma * sigma))  # (n_w, n_w), symmetric
            weights = (h @ sums) / (h @ counts).clamp(min=torch.finfo(data.dtype).tiny).unsqueeze(-1)
        return weights

    def _select(self, modes: torch.Tensor, time: torch.Tensor) -> torch.Tensor:
        data = self.training_data(modes, time)
        weights = self.train_map(data)
        self.weights_ = weights
        # Neuron times back to samples: nearest free sample to each neuron's time component.
        t_scaled = data[:, 0]
        taken = torch.zeros(data.shape[0], dtype=torch.bool)
        chosen = []
        for tw in weights[:, 0]:
            dist = (t_scaled - tw).abs()
            dist[taken] = torch.inf
            i = int(torch.argmin(dist))
            taken[i] = True
            chosen.append(i)
        return self._conditioned(modes, time, torch.tensor(chosen))

    def _conditioned(self, modes: torch.Tensor, time: torch.Tensor, chosen: torch.Tensor) -> torch.Tensor:
        """The map's points, or, where they leave G worse than ``max_condition``, the fewest of them exchanged
        (:func:`exchange_points`); the greedy E-optimal set only where the exchange cannot reach the bound and
        the greedy set does better."""
        self.condition_, self.fallback_ = gram_condition(modes, chosen), None
        if self.max_condition is None or self.condition_ <= self.max_condition or self.n_points <= modes.shape[1]:
            return chosen
        som_condition = self.condition_
        kept, _, condition = exchange_points(modes, chosen, self.max_condition)
        how = "exchanged {replaced} of its points"
        if condition > self.max_condition:
            greedy = GreedySelector(self.n_points)._select(modes, time)
            greedy_condition = gram_condition(modes, greedy)
            if greedy_condition < condition:
                kept, condition, how = greedy, greedy_condition, "kept the greedy E-optimal points"
        if not condition < som_condition:
            return chosen
        replaced = int((~torch.isin(kept, chosen)).sum())  # a swap may bring back a point an earlier one removed
        log.warning(
            "selector som: its %d points leave the gappy matrix with condition number %.0f (> max_condition %.0f); "
            "%s (condition %.0f)",
            self.n_points,
            som_condition,
            self.max_condition,
            how.format(replaced=replaced),
            condition,
        )
        self.fallback_ = {"replaced": replaced, "som_condition": som_condition, "condition": condition}
        self.condition_ = condition
        return kept

    def get_params(self) -> dict[str, object]:
        return {
            **super().get_params(),
            "map_shape": list(self.map_shape),
            "time_weight": self.time_weight,
            "column_scaling": self.column_scaling,
            "epochs": self.epochs,
            "sigma_start": self.sigma_start,
            "sigma_end": self.sigma_end,
            "max_condition": self.max_condition,
        }
