"""Primal squared-hinge SVM training shared by the explicit-feature classifiers (float64 L-BFGS).

Minimises 0.5 ||beta||^2 + C sum_i c_i max(0, 1 - y_i (phi_i . beta + b))^2 over (beta, b): the L2-SVM
of the kernel whose feature map is phi. The objective is convex and continuously differentiable, so
L-BFGS with a strong-Wolfe line search reaches the unique optimum (no support-vector bookkeeping).
"""

from __future__ import annotations

import torch

CLASS_WEIGHTS = (None, "balanced")


def sample_weights(y: torch.Tensor, class_weight: str | None) -> torch.Tensor:
    """(N,) per-sample weights c_i: ones, or N / (2 N_class) with ``balanced``."""
    if class_weight not in CLASS_WEIGHTS:
        raise ValueError(f"classifier.class_weight must be null or 'balanced', got {class_weight!r}")
    if class_weight is None:
        return torch.ones_like(y)
    n = y.numel()
    pos = float((y > 0).sum())
    return torch.where(y > 0, n / (2.0 * pos), n / (2.0 * (n - pos)))


def fit_squared_hinge(
    features: torch.Tensor, y: torch.Tensor, c: float, weights: torch.Tensor, max_iter: int, tol: float
) -> tuple[torch.Tensor, torch.Tensor, int]:
    """(beta (F,), b (), iterations) for features (N, F) float64 and labels y (N,) in {-1, +1}."""
    beta = torch.zeros(features.shape[1], dtype=torch.float64, requires_grad=True)
    bias = torch.zeros((), dtype=torch.float64, requires_grad=True)
    opt = torch.optim.LBFGS(
        [beta, bias],
        lr=1.0,
        max_iter=max_iter,
        tolerance_grad=tol,
        tolerance_change=1e-14,
        history_size=20,
        line_search_fn="strong_wolfe",
    )

    def closure() -> torch.Tensor:
        opt.zero_grad()
        margin = (1.0 - y * (features @ beta + bias)).clamp(min=0.0)
        loss = 0.5 * beta.pow(2).sum() + c * (weights * margin.pow(2)).sum()
        loss.backward()
        return loss

    with torch.enable_grad():
        opt.step(closure)
    n_iter = int(opt.state[opt._params[0]].get("n_iter", 0))
    return beta.detach(), bias.detach(), n_iter
