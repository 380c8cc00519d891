"""Levenberg-Marquardt with batched finite-difference Jacobians.

The simulators are batched, so the n + 1 evaluations of a forward-difference Jacobian, and the trial
steps for several damping values, each cost one simulator call: a fit of a handful of parameters
through a 10^4-step simulation takes seconds, with no graph to keep for backpropagation.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import torch


@dataclass
class LMResult:
    """Outcome of a fit.

    Attributes:
        x: parameters (n,).  cost: 0.5 * ||r||^2 at x.  residual: r(x) (m,).
        jacobian: dr/dx at x (m, n).  iterations: number of accepted steps.  converged: tolerance met.
        history: cost after each iteration.
    """

    x: torch.Tensor
    cost: float
    residual: torch.Tensor
    jacobian: torch.Tensor
    iterations: int
    converged: bool
    history: list[float]

    def covariance(self, noise_variance: float | None = None) -> torch.Tensor:
        """Gauss-Newton (Laplace) covariance sigma^2 (J^T J)^-1; sigma^2 from the residual if not given."""
        m, n = self.jacobian.shape
        s2 = noise_variance if noise_variance is not None else 2.0 * self.cost / max(m - n, 1)
        jtj = self.jacobian.T @ self.jacobian
        return s2 * torch.linalg.pinv(jtj)


def batched_levenberg_marquardt(residuals: Callable[[torch.Tensor], torch.Tensor], x0: torch.Tensor,
                                lower: torch.Tensor | None = None, upper: torch.Tensor | None = None,
                                step: torch.Tensor | float = 1e-4, max_iter: int = 20, damping: float = 1e-3,
                                tol: float = 1e-6) -> LMResult:
    """Minimise 0.5 ||r(x)||^2 within box bounds.

    Args:
        residuals: maps a batch of parameter vectors (P, n) to residual vectors (P, m) in one call.
        x0: start (n,).  lower, upper: bounds (n,) (steps are clipped to them).
        step: forward-difference step, absolute, scalar or (n,).
        max_iter: iterations (each = one Jacobian call + one trial call).
        damping: initial lambda of the Marquardt scaling diag(J^T J).
        tol: stop when the relative cost decrease falls below tol.
    """
    x = x0.detach().clone().to(torch.float64)
    n = x.numel()
    lo = lower if lower is not None else torch.full_like(x, -torch.inf)
    hi = upper if upper is not None else torch.full_like(x, torch.inf)
    if ((x < lo) | (x > hi)).any():
        raise ValueError(f"x0 {x.tolist()} is outside the bounds [{lo.tolist()}, {hi.tolist()}]")
    h = torch.as_tensor(step, dtype=x.dtype).expand(n).clone()
    lam, history, converged, it = damping, [], False, 0
    r = jac = None
    cost = float("inf")
    for it in range(1, max_iter + 1):
        # Step away from an upper bound backwards so that every probe stays feasible.
        hs = torch.where(x + h > hi, -h, h)
        probes = torch.cat([x.unsqueeze(0), x.unsqueeze(0) + torch.diag(hs)])
        res = residuals(probes).detach().to(torch.float64)
        r = res[0]
        cost = 0.5 * float(r @ r)
        jac = ((res[1:] - r) / hs.unsqueeze(-1)).T                      # (m, n)
        g = jac.T @ r
        a = jac.T @ jac
        diag = torch.diag(a).clamp(min=1e-12 * float(torch.diag(a).max().clamp(min=1e-300)))
        lams = torch.tensor([lam * 0.1, lam, lam * 10.0, lam * 100.0], dtype=x.dtype)
        trials = []
        for lm in lams:
            dx = torch.linalg.solve(a + lm * torch.diag(diag), -g)
            trials.append(torch.minimum(torch.maximum(x + dx, lo), hi))
        trial_x = torch.stack(trials)
        trial_r = residuals(trial_x).detach().to(torch.float64)
        trial_cost = 0.5 * (trial_r * trial_r).sum(-1)
        best = int(torch.argmin(trial_cost))
        history.append(cost)
        if float(trial_cost[best]) < cost:
            rel = (cost - float(trial_cost[best])) / max(cost, 1e-300)
            x, lam = trial_x[best], float(lams[best])
            r, cost = trial_r[best], float(trial_cost[best])
            if rel < tol:
                converged = True
                break
        else:
            lam *= 100.0
            if lam > 1e8:
                converged = True
                break
    # Final Jacobian at the solution for the covariance.
    hs = torch.where(x + h > hi, -h, h)
    res = residuals(torch.cat([x.unsqueeze(0), x.unsqueeze(0) + torch.diag(hs)])).detach().to(torch.float64)
    r = res[0]
    jac = ((res[1:] - r) / hs.unsqueeze(-1)).T
    return LMResult(x, 0.5 * float(r @ r), r, jac, it, converged, history)
