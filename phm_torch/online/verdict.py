"""Probability that an actuator is faulty, from the verdict score of its FDI estimate (Platt scaling).

The health score f(k_hat) of an *estimated* fault vector gets the verdict right 83-93 % of the time on
paper-scale signals, against 99 % for the true k: the FDI error moves vectors across the boundary. The
verdict classifier fitted on estimates (:mod:`phm_torch.surrogates.verdict_classifier`) raises that to
about 95 % (``chain_accuracy`` of phm-train), still not 99 %, and the sign of the score hides which
records are the doubtful ones. :func:`calibrate_verdict` fits P(faulty | s) = sigmoid(a s + b) to
held-out records (phm-evaluate: the FDI band's split, with its measurement noise), so that a score near
the boundary reads as a coin toss and a clear one as near-certain; the online pipeline carries (a, b)
and returns the probability.
"""

from __future__ import annotations

import math

import torch


def calibrate_verdict(
    score: torch.Tensor, faulty: torch.Tensor, ridge: float = 1e-3, iterations: int = 100
) -> tuple[float, float]:
    """Platt scaling of health scores: (a, b) of P(faulty | s) = sigmoid(a s + b).

    Newton's method on the mean logistic loss of the standardised score, with a small ridge so that
    separable data still give a finite (steep) slope.

    Args:
        score: (N,) health scores f(k_hat) of held-out records (> 0 healthy).
        faulty: (N,) bool, the records' actual health (True = faulty).
        ridge: L2 weight on the standardised slope and offset.
        iterations: most Newton steps.

    Returns:
        (a, b) with a < 0 when a higher score means healthier, as it should.
    """
    score, faulty = torch.as_tensor(score, dtype=torch.float64), torch.as_tensor(faulty)
    if score.ndim != 1 or faulty.shape != score.shape:
        raise ValueError(f"score and faulty must both be (N,), got {tuple(score.shape)} and {tuple(faulty.shape)}")
    if not bool(torch.isfinite(score).all()):
        raise ValueError("score must be finite (drop out-of-distribution records first)")
    y = faulty.to(torch.float64)
    if not 0 < float(y.sum()) < y.numel():
        raise ValueError(
            f"calibrating the verdict needs healthy and faulty records, got {int(y.sum())} faulty of {y.numel()}"
        )
    center, spread = score.mean(), score.std().clamp(min=1e-12)
    x = torch.stack([(score - center) / spread, torch.ones_like(score)], 1)  # (N, 2)
    w = torch.zeros(2, dtype=torch.float64)
    eye = torch.eye(2, dtype=torch.float64)
    for _ in range(iterations):
        p = torch.sigmoid(x @ w)
        grad = x.T @ (p - y) / len(y) + ridge * w
        hess = (x.T * (p * (1 - p))) @ x / len(y) + ridge * eye
        step = torch.linalg.solve(hess, grad)
        w = w - step
        if float(step.abs().max()) < 1e-10:
            break
    a = float(w[0] / spread)
    return a, float(w[1] - a * center)


def shift_prior(offset: float, calibration_prior: float, prior: float) -> float:
    """The offset b of a Platt law fitted where a fraction ``calibration_prior`` of the records was faulty,
    moved to a population where ``prior`` is (Bayes: the likelihood ratio stays, the prior odds change)."""
    for name, value in (("calibration_prior", calibration_prior), ("prior", prior)):
        if not 0.0 < value < 1.0:
            raise ValueError(f"{name} must be in (0, 1), got {value!r}")
    return offset + math.log(prior / (1 - prior)) - math.log(calibration_prior / (1 - calibration_prior))


def verdict_quality(p_faulty: torch.Tensor, faulty: torch.Tensor) -> dict[str, float | None]:
    """Brier score of P(faulty) (N,) against the actual health (N,) bool, beside that of the constant base
    rate (what a verdict without information scores; None where the records hold one class only: the base rate
    then scores 0 with hindsight, and nothing compares with it), the faulty fraction, and the accuracy of p > 0.5."""
    p, y = p_faulty.to(torch.float64), faulty.to(torch.float64)
    rate = float(y.mean())
    return {
        "brier": float((p - y).pow(2).mean()),
        "brier_base_rate": float((rate - y).pow(2).mean()) if 0.0 < rate < 1.0 else None,
        "faulty_fraction": rate,
        "accuracy": float(((p > 0.5).to(torch.float64) == y).to(torch.float64).mean()),
    }
