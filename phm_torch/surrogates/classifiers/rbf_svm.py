"""Gaussian-kernel SVM through a Nystrom feature map (an alternative to the paper's polynomial kernel).

With m landmarks L (a seeded random subset of the standardised training vectors), the feature map
phi(z) = K(z, L) K(L, L)^-1/2 makes phi(z).phi(z') the Nystrom approximation of the kernel
exp(-gamma ||z - z'||^2); a linear squared-hinge SVM on phi follows (see ``training.py``). The score
f(k) = phi(z(k)) . beta + b is smooth (a sum of m Gaussians) and costs one (B, m) kernel evaluation.
"""

from __future__ import annotations

import math
from typing import Any

import torch

from ...faults import N_FAULTS
from .base import FeatureMapSVM, check_training_set, check_warp, warp_inputs
from .training import sample_weights


class RBFSVM(FeatureMapSVM):
    """Squared-hinge SVM with a Nystrom-approximated Gaussian kernel.

    Args:
        n_landmarks: m, the number of landmark vectors (capped at the training-set size).
        gamma: kernel width on standardised inputs; ``None`` = 1 / 8.
        C: soft-margin penalty (> 0).
        class_weight: ``None`` or ``balanced``.
        seed: seed of the landmark draw.
        max_iter, tol: L-BFGS settings.
        warp: input warp x(k) before standardisation, ``none`` or ``sqrt`` (see ``base.warp_inputs``).
    """

    name = "rbf_svm"

    def __init__(
        self,
        n_landmarks: int = 300,
        gamma: float | None = None,
        C: float = 1.0,
        class_weight: str | None = None,
        seed: int = 0,
        max_iter: int = 500,
        tol: float = 1e-9,
        warp: str = "none",
    ):
        super().__init__()
        if isinstance(n_landmarks, bool) or not isinstance(n_landmarks, int) or n_landmarks < 2:
            raise ValueError(f"classifier.n_landmarks must be an integer >= 2, got {n_landmarks!r}")
        g = 1.0 / N_FAULTS if gamma is None else gamma
        if not (math.isfinite(g) and g > 0):
            raise ValueError(f"classifier.gamma must be > 0, got {gamma!r}")
        if not (math.isfinite(C) and C > 0):
            raise ValueError(f"classifier.C must be > 0, got {C!r}")
        sample_weights(torch.tensor([1.0, -1.0]), class_weight)
        self.n_landmarks, self.gamma, self.C, self.class_weight = n_landmarks, gamma, float(C), class_weight
        self.seed, self.max_iter, self.tol = seed, max_iter, tol
        self.warp = check_warp(warp)
        self._g = float(g)
        self.register_buffer("k_mean", torch.zeros(N_FAULTS, dtype=torch.float64))
        self.register_buffer("k_std", torch.ones(N_FAULTS, dtype=torch.float64))
        self.register_buffer("landmarks", torch.zeros(0, N_FAULTS, dtype=torch.float64))
        self.register_buffer("whitening", torch.zeros(0, 0, dtype=torch.float64))
        self.register_buffer("beta", torch.zeros(0, dtype=torch.float64))
        self.register_buffer("bias", torch.zeros((), dtype=torch.float64))
        self.register_buffer("kernel_gamma", torch.tensor(self._g, dtype=torch.float64))

    def _kernel(self, a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
        return torch.exp(-self.kernel_gamma * torch.cdist(a, b).pow(2))

    def features(self, k: torch.Tensor) -> torch.Tensor:
        """phi(z(k)) (B, m)."""
        z = (warp_inputs(k.to(self.k_mean.dtype), self.warp) - self.k_mean) / self.k_std
        return self._kernel(z, self.landmarks) @ self.whitening

    def fit(self, k: torch.Tensor, healthy: torch.Tensor) -> RBFSVM:
        k64, y = check_training_set(k, healthy)
        x = warp_inputs(k64, self.warp)
        self.k_mean, self.k_std = x.mean(0), x.std(0).clamp(min=1e-12)
        z = (x - self.k_mean) / self.k_std
        m = min(self.n_landmarks, z.shape[0])
        pick = torch.randperm(z.shape[0], generator=torch.Generator().manual_seed(self.seed))[:m]
        self.landmarks = z[pick]
        evals, evecs = torch.linalg.eigh(self._kernel(self.landmarks, self.landmarks))
        keep = evals > evals.max() * 1e-10  # drop the numerically null part
        self.whitening = evecs[:, keep] / evals[keep].sqrt()
        self._fit_linear(k64, y)
        return self

    def get_params(self) -> dict[str, Any]:
        return {
            "n_landmarks": self.n_landmarks,
            "gamma": self.gamma,
            "C": self.C,
            "class_weight": self.class_weight,
            "seed": self.seed,
            "max_iter": self.max_iter,
            "tol": self.tol,
            "warp": self.warp,
        }
