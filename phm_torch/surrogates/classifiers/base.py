"""Health-classifier interface: a smooth score f(k) of the fault vector, positive = healthy.

The score replaces the assessment function phi_a(k) (seed paper, "Offline: learning a model for the
assessment of the health status"): sign(f(k)) is the predicted label, and f itself, being smooth and
cheap, can serve as the event function that stops the damage-propagation integration (RUL) where it
crosses zero. Classifiers are ``nn.Module``s whose ``forward`` is the score, so they move to a device and
export with the rest of the surrogates; ``fit`` is plain Python (deterministic).

Input warp (``warp`` argument of every classifier): the importance-sampled fault vectors crowd near 0
(median entry ~0.05, a quarter below 5e-4 on the paper store) while the health boundary bends there, so
the classifiers may see x = sqrt(max(k, 0) + WARP_EPS) instead of k (``warp="sqrt"``), which spreads the
small values out. WARP_EPS keeps the warp, and hence the score, differentiable at k = 0 (slope
1 / (2 sqrt(WARP_EPS)) = 50 there instead of infinite): the score is the RUL integration's stopping event.
"""

from __future__ import annotations

import abc
from typing import Any, ClassVar

import torch
from torch import nn

from ...faults import N_FAULTS

WARPS = ("none", "sqrt")
WARP_EPS = 1e-4  # sqrt warp offset: sqrt(1e-4) = 0.01, small against the typical sqrt(k) ~ 0.2


def check_warp(warp: str) -> str:
    """``warp`` validated (one of :data:`WARPS`)."""
    if warp not in WARPS:
        raise ValueError(f"classifier.warp must be one of {list(WARPS)}, got {warp!r}")
    return warp


def warp_inputs(k: torch.Tensor, warp: str, eps: float = WARP_EPS) -> torch.Tensor:
    """The classifier inputs x (B, 8) of fault vectors k (B, 8): k itself (``none``) or
    sqrt(max(k, 0) + eps) (``sqrt``); same dtype as k. TorchScript-compatible."""
    if warp == "sqrt":
        return torch.sqrt(k.clamp(min=0.0) + eps)
    return k


def check_training_set(k: torch.Tensor, healthy: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Validated float64 (N, 8) fault vectors and float64 (N,) labels +1 (healthy) / -1 (faulty)."""
    if k.ndim != 2 or k.shape[1] != N_FAULTS:
        raise ValueError(f"classifier: k must be (N, {N_FAULTS}), got {tuple(k.shape)}")
    if healthy.shape != k.shape[:1]:
        raise ValueError(f"classifier: labels must be ({k.shape[0]},) like k, got {tuple(healthy.shape)}")
    if not torch.isfinite(k).all():
        raise ValueError("classifier: k contains NaN or inf")
    h = healthy.bool()
    if bool(h.all()) or not bool(h.any()):
        raise ValueError(
            f"classifier: the training labels must contain both classes, got {int(h.sum())} healthy of {h.numel()}"
        )
    return k.to(torch.float64), torch.where(h, 1.0, -1.0).to(torch.float64)


class HealthClassifier(nn.Module, abc.ABC):
    """Base class: ``fit(k, healthy)``, ``forward(k) -> score`` (B,), ``predict(k) -> healthy`` (B,) bool.

    Subclasses set ``name``, implement :meth:`fit`, :meth:`forward` and :meth:`get_params` (constructor
    arguments, so that the registry can rebuild an unfitted twin and load the fitted buffers into it).
    Every fitted quantity is a buffer; ``threshold`` (buffer, 0 unless :meth:`calibrate` moved it) shifts
    the decision: healthy iff f(k) > threshold, so f(k) - threshold is the score with the sign convention.
    """

    name: ClassVar[str] = ""

    def __init__(self) -> None:
        super().__init__()
        self.n_features = N_FAULTS
        self.register_buffer("threshold", torch.zeros((), dtype=torch.float64))

    @abc.abstractmethod
    def fit(self, k: torch.Tensor, healthy: torch.Tensor) -> HealthClassifier:
        """Fit to fault vectors k (N, 8) in [0, 1] and labels ``healthy`` (N,) bool; returns self."""

    @abc.abstractmethod
    def get_params(self) -> dict[str, Any]:
        """Constructor arguments."""

    @torch.no_grad()
    def calibrate(self, k: torch.Tensor, healthy: torch.Tensor, max_missed_fault_rate: float) -> HealthClassifier:
        """Raise ``threshold`` (never lower it below 0) until at most ``max_missed_fault_rate`` of the faulty
        vectors of (k (N, 8), healthy (N,)) score above it: fewer missed faults for more false alarms."""
        if not 0.0 <= max_missed_fault_rate < 1.0:
            raise ValueError(f"calibration.max_missed_fault_rate must be in [0, 1), got {max_missed_fault_rate!r}")
        faulty = self(k)[~healthy.bool()]
        if faulty.numel() == 0:
            raise ValueError("classifier.calibrate: no faulty vector in the calibration set")
        level = torch.quantile(faulty.to(torch.float64), 1.0 - max_missed_fault_rate)
        self.threshold = torch.clamp(level, min=0.0).to(self.threshold)
        return self

    def predict(self, k: torch.Tensor) -> torch.Tensor:
        """(B,) True where the score says healthy."""
        return self(k) > self.threshold

    def check_input(self, k: torch.Tensor) -> None:
        if k.dim() != 2 or k.shape[1] != self.n_features:
            raise ValueError(f"k must be (B, {self.n_features}), got {list(k.shape)}")


class FeatureMapSVM(HealthClassifier):
    """A score linear in a fixed feature map, f(k) = phi(k) . beta + bias, fitted as a squared-hinge SVM.

    Subclasses define ``features`` (and set up the map in ``fit`` before calling :meth:`_fit_linear`);
    they must register the buffers ``beta`` and ``bias`` and the attributes ``C``, ``class_weight``,
    ``max_iter`` and ``tol``.
    """

    @abc.abstractmethod
    def features(self, k: torch.Tensor) -> torch.Tensor:
        """phi(k) (B, F) of fault vectors (B, 8)."""

    def _fit_linear(self, k64: torch.Tensor, y: torch.Tensor) -> None:
        from .training import fit_squared_hinge, sample_weights

        beta, bias, n_iter = fit_squared_hinge(
            self.features(k64), y, self.C, sample_weights(y, self.class_weight), self.max_iter, self.tol
        )
        self.beta, self.bias = beta, bias
        self.n_iter_ = n_iter

    def forward(self, k: torch.Tensor) -> torch.Tensor:
        """Score f(k) (B,): > 0 healthy, < 0 faulty."""
        self.check_input(k)
        return self.features(k) @ self.beta + self.bias
