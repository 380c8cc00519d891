"""Tanh multilayer-perceptron health classifier: a smooth learned score f(k), the network's logit.

The inputs are the warped fault vectors x(k) (``warp``, see ``base.warp_inputs``; ``sqrt`` by default)
standardised with their training mean and std, z = (x - k_mean) / k_std; then tanh hidden layers and a
linear output:

    f(k) = w_L . tanh(W_{L-1} ... tanh(W_1 z + b_1) ... + b_{L-1}) + b_L      (positive = healthy)

trained with binary cross-entropy on the logit f (label 1 = healthy), so f = 0 is the p = 1/2 decision
and :meth:`~.base.HealthClassifier.calibrate` shifts it like the SVM margins. f is infinitely
differentiable in k (>= 0; the sqrt warp has slope 50 at k = 0), which the RUL stopping event needs.

All weights live in one flat buffer (``flat_weights``; layer i's weight (n_out, n_in) then its bias
(n_out,), in the order of :func:`mlp_layout`) so that the bundle, which saves and restores a classifier's
top-level buffers and rebuilds the layout from ``get_params()``, round-trips it, and ``torch.jit.script``
compiles the forward (a loop of ``F.linear`` + ``tanh`` over views of that buffer).
"""

from __future__ import annotations

import math
import time
from collections.abc import Sequence
from typing import Any

import torch
import torch.nn.functional as F

from ...faults import N_FAULTS
from .base import HealthClassifier, check_training_set, check_warp, warp_inputs
from .training import sample_weights

DTYPES = {"float32": torch.float32, "float64": torch.float64}
SCHEDULES = ("cosine", "constant")


def mlp_layout(hidden: Sequence[int], n_in: int = N_FAULTS) -> list[tuple[int, int, int]]:
    """(offset, n_out, n_in) of every linear layer (hidden ones, then the 1-unit output) in the flat weight
    vector: the weight (n_out, n_in) starts at offset, its bias (n_out,) follows."""
    layout, offset = [], 0
    for n_out in [*hidden, 1]:
        layout.append((offset, n_out, n_in))
        offset += n_out * (n_in + 1)
        n_in = n_out
    return layout


def n_weights(layout: list[tuple[int, int, int]]) -> int:
    """Length of the flat weight vector of ``layout``."""
    offset, n_out, n_in = layout[-1]
    return offset + n_out * (n_in + 1)


def mlp_forward(z: torch.Tensor, flat: torch.Tensor, layout: list[tuple[int, int, int]]) -> torch.Tensor:
    """Logits (B,) of inputs z (B, n_in): tanh hidden layers, linear output; weights are views into flat (P,)."""
    h = z
    last = len(layout) - 1
    for i, spec in enumerate(layout):
        offset, n_out, n_in = spec
        end = offset + n_out * n_in
        h = F.linear(h, flat[offset:end].view(n_out, n_in), flat[end : end + n_out])
        if i < last:
            h = torch.tanh(h)
    return h.squeeze(1)


def glorot_init(layout: list[tuple[int, int, int]], generator: torch.Generator, dtype: torch.dtype) -> torch.Tensor:
    """Flat weights (P,): Glorot-uniform weights (drawn from ``generator``), zero biases."""
    flat = torch.zeros(n_weights(layout), dtype=dtype)
    for offset, n_out, n_in in layout:
        bound = math.sqrt(6.0 / (n_in + n_out))
        flat[offset : offset + n_out * n_in].uniform_(-bound, bound, generator=generator)
    return flat


def _positive_int(value: Any, field: str) -> int:
    if isinstance(value, bool) or not isinstance(value, int) or value < 1:
        raise ValueError(f"classifier.{field} must be a positive integer, got {value!r}")
    return value


class MLPClassifier(HealthClassifier):
    """Tanh MLP on the standardised warped fault vectors, trained with (weighted) BCE on its logit.

    Args:
        hidden: widths of the hidden layers (non-empty list of positive integers).
        warp: input warp x(k), ``sqrt`` (default) or ``none``.
        epochs: passes over the training set.
        batch_size: minibatch size (the last batch of an epoch may be smaller).
        lr: AdamW learning rate (> 0); the peak of the ``cosine`` schedule.
        weight_decay: AdamW decoupled weight decay (>= 0; 0 = Adam).
        schedule: ``cosine`` (lr annealed to 0 over the epochs, per epoch) or ``constant``.
        class_weight: ``None`` or ``balanced`` (per-sample BCE weights, ``training.sample_weights``).
        seed: seed of the initialisation and of the minibatch order (training is deterministic on CPU).
        dtype: ``float32`` or ``float64``, the dtype of the weights, of training and of the forward
            (inputs are cast to it; the score is returned in the dtype of ``threshold``, float64).

    Fitted: buffers ``k_mean``, ``k_std`` (8,) and ``flat_weights`` (P,); attributes ``n_epochs_``,
    ``train_loss_`` (mean training loss per epoch), ``fit_seconds_``.
    """

    name = "mlp"

    def __init__(
        self,
        hidden: Sequence[int] = (64, 64, 64),
        warp: str = "sqrt",
        epochs: int = 150,
        batch_size: int = 512,
        lr: float = 1e-3,
        weight_decay: float = 0.0,
        schedule: str = "cosine",
        class_weight: str | None = None,
        seed: int = 0,
        dtype: str = "float32",
    ):
        super().__init__()
        if (
            isinstance(hidden, (str, bytes))
            or not isinstance(hidden, Sequence)
            or len(hidden) == 0
            or any(isinstance(h, bool) or not isinstance(h, int) or h < 1 for h in hidden)
        ):
            raise ValueError(f"classifier.hidden must be a non-empty list of positive integers, got {hidden!r}")
        self.hidden = [int(h) for h in hidden]
        self.warp = check_warp(warp)
        self.epochs = _positive_int(epochs, "epochs")
        self.batch_size = _positive_int(batch_size, "batch_size")
        if isinstance(lr, bool) or not isinstance(lr, (int, float)) or not (math.isfinite(lr) and lr > 0):
            raise ValueError(f"classifier.lr must be > 0, got {lr!r}")
        if (
            isinstance(weight_decay, bool)
            or not isinstance(weight_decay, (int, float))
            or not (math.isfinite(weight_decay) and weight_decay >= 0)
        ):
            raise ValueError(f"classifier.weight_decay must be >= 0, got {weight_decay!r}")
        if schedule not in SCHEDULES:
            raise ValueError(f"classifier.schedule must be one of {list(SCHEDULES)}, got {schedule!r}")
        sample_weights(torch.tensor([1.0, -1.0]), class_weight)  # validates the name
        if isinstance(seed, bool) or not isinstance(seed, int):
            raise ValueError(f"classifier.seed must be an integer, got {seed!r}")
        if dtype not in DTYPES:
            raise ValueError(f"classifier.dtype must be one of {list(DTYPES)}, got {dtype!r}")
        self.lr, self.weight_decay, self.schedule = float(lr), float(weight_decay), schedule
        self.class_weight, self.seed, self.dtype = class_weight, seed, dtype
        self.layout = mlp_layout(self.hidden)
        dt = DTYPES[dtype]
        self.register_buffer("k_mean", torch.zeros(N_FAULTS, dtype=dt))
        self.register_buffer("k_std", torch.ones(N_FAULTS, dtype=dt))
        self.register_buffer("flat_weights", torch.zeros(n_weights(self.layout), dtype=dt))

    def forward(self, k: torch.Tensor) -> torch.Tensor:
        """Score f(k) (B,) (the logit; > 0 healthy) of fault vectors k (B, 8), in the dtype of ``threshold``."""
        self.check_input(k)
        x = warp_inputs(k.to(self.flat_weights.dtype), self.warp)
        z = (x - self.k_mean) / self.k_std
        return mlp_forward(z, self.flat_weights, self.layout).to(self.threshold.dtype)

    def fit(self, k: torch.Tensor, healthy: torch.Tensor) -> MLPClassifier:
        """Train on fault vectors k (N, 8) and labels ``healthy`` (N,) bool; returns self."""
        t0 = time.perf_counter()
        k64, y = check_training_set(k, healthy)
        dt = DTYPES[self.dtype]
        x = warp_inputs(k64, self.warp)
        mean, std = x.mean(0), x.std(0).clamp(min=1e-12)
        z = ((x - mean) / std).to(dt)
        target = (y > 0).to(dt)
        weight = sample_weights(y, self.class_weight).to(dt)
        gen = torch.Generator().manual_seed(self.seed)
        flat = glorot_init(self.layout, gen, dt).requires_grad_(True)
        opt = torch.optim.AdamW([flat], lr=self.lr, weight_decay=self.weight_decay)
        n, losses = z.shape[0], []
        with torch.enable_grad():
            for epoch in range(self.epochs):
                if self.schedule == "cosine":
                    opt.param_groups[0]["lr"] = 0.5 * self.lr * (1.0 + math.cos(math.pi * epoch / self.epochs))
                order = torch.randperm(n, generator=gen)
                total = 0.0
                for start in range(0, n, self.batch_size):
                    idx = order[start : start + self.batch_size]
                    loss = F.binary_cross_entropy_with_logits(
                        mlp_forward(z[idx], flat, self.layout), target[idx], weight=weight[idx]
                    )
                    opt.zero_grad(set_to_none=True)
                    loss.backward()
                    opt.step()
                    total += float(loss.detach()) * idx.numel()
                losses.append(total / n)
        self.k_mean, self.k_std = mean.to(dt), std.to(dt)
        self.flat_weights = flat.detach()
        self.n_epochs_, self.train_loss_ = self.epochs, losses
        self.fit_seconds_ = time.perf_counter() - t0
        return self

    def get_params(self) -> dict[str, Any]:
        return {
            "hidden": list(self.hidden),
            "warp": self.warp,
            "epochs": self.epochs,
            "batch_size": self.batch_size,
            "lr": self.lr,
            "weight_decay": self.weight_decay,
            "schedule": self.schedule,
            "class_weight": self.class_weight,
            "seed": self.seed,
            "dtype": self.dtype,
        }
