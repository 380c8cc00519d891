"""Levenberg-Marquardt for several independent fits sharing one batched simulator call per iteration.

Each iteration of each problem proposes trial steps for a few damping values and evaluates every trial
*together with its forward-difference Jacobian* (trials x (n + 1) rows). The best trial is accepted with
its Jacobian already known, so an iteration costs exactly one simulator call, and the calls of all
problems still running (e.g. the refits of the top candidates) are merged into one batch: a batched
simulation costs about the same for 10 or 100 rows.

Residuals are normalised (divided by the noise standard deviation), so the cost 0.5 ||r||^2 is half a
chi-square and the Gauss-Newton (Laplace) covariance is s^2 (J^T J)^-1 with s^2 = ||r||^2 / (m - n).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

import torch

# evaluate([(j, X (P, n_j))]) -> [(R (P, m_j), payload)]: rows X of problem j; payload[i] is kept for row i.
Evaluate = Callable[[list[tuple[int, torch.Tensor]]], list[tuple[torch.Tensor, Any]]]


@dataclass
class Problem:
    """One fit: start, box bounds and forward-difference steps, each (n,); optional Gaussian prior
    (residuals ``prior_weight * (x - prior_mean)`` appended, e.g. a ridge penalty)."""

    x0: torch.Tensor
    lower: torch.Tensor
    upper: torch.Tensor
    step: torch.Tensor
    prior_weight: torch.Tensor | None = None
    prior_mean: torch.Tensor | None = None

    def __post_init__(self) -> None:
        self.x0 = self.x0.to(torch.float64)
        if ((self.x0 < self.lower) | (self.x0 > self.upper)).any():
            bad = int(((self.x0 < self.lower) | (self.x0 > self.upper)).nonzero()[0])
            raise ValueError(f"start value x0[{bad}] = {float(self.x0[bad]):.6g} is outside its bounds "
                             f"[{float(self.lower[bad]):.6g}, {float(self.upper[bad]):.6g}]")

    def augment(self, r: torch.Tensor, jac: torch.Tensor, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Residual and Jacobian with the prior rows appended."""
        if self.prior_weight is None:
            return r, jac
        mean = self.prior_mean if self.prior_mean is not None else torch.zeros_like(x)
        return (torch.cat([r, self.prior_weight * (x - mean)]),
                torch.cat([jac, torch.diag(self.prior_weight)]))


@dataclass
class FitResult:
    """Outcome of one fit.

    Attributes:
        x: (n,).  residual: r(x) (m,), prior excluded.  jacobian: dr/dx (m, n).  cost: 0.5 ||r||^2 (prior
        included).  iterations, converged, history (cost per iteration).  payload: evaluate's data of x.
    """

    x: torch.Tensor
    residual: torch.Tensor
    jacobian: torch.Tensor
    cost: float
    iterations: int = 0
    converged: bool = False
    history: list[float] = field(default_factory=list)
    payload: Any = None

    @property
    def chi2(self) -> float:
        """||r||^2 of the data residual (prior excluded)."""
        return float(self.residual @ self.residual)

    def covariance(self, problem: Problem | None = None) -> torch.Tensor:
        """Gauss-Newton/Laplace covariance s^2 (J^T J + prior)^-1 of x, s^2 = ||r||^2 / (m - n)."""
        m, n = self.jacobian.shape
        s2 = self.chi2 / max(m - n, 1)
        a = self.jacobian.T @ self.jacobian
        if problem is not None and problem.prior_weight is not None:
            a = a + torch.diag(problem.prior_weight ** 2)
        return s2 * torch.linalg.pinv(a)

    def std(self, problem: Problem | None = None) -> torch.Tensor:
        return self.covariance(problem).diagonal().clamp(min=0.0).sqrt()


def probe_rows(x: torch.Tensor, problem: Problem) -> tuple[torch.Tensor, torch.Tensor]:
    """[x; x + h_i e_i] (n + 1, n) and the signed steps h (n,) (backwards at an upper bound)."""
    h = torch.where(x + problem.step > problem.upper, -problem.step, problem.step)
    return torch.cat([x.unsqueeze(0), x.unsqueeze(0) + torch.diag(h)]), h


def jacobian(res: torch.Tensor, h: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Residual r (m,) and forward-difference Jacobian (m, n) from probe residuals (n + 1, m)."""
    r = res[0]
    return r, ((res[1:] - r) / h.unsqueeze(-1)).T


def fit(evaluate: Evaluate, problems: Sequence[Problem], max_iter: int = 8, lambdas: Sequence[float] = (0.1, 1.0, 10.0),
        damping: float = 1e-2, tol_abs: float = 0.5, tol_rel: float = 1e-4,
        start: Sequence[FitResult | None] | None = None, on_iteration: Callable[[int, list[float]], None] | None = None
        ) -> list[FitResult]:
    """Minimise 0.5 ||r_j(x)||^2 (+ prior) for every problem j, sharing evaluate calls.

    Args:
        evaluate: see :data:`Evaluate`.
        problems: the fits.
        max_iter: iterations (one evaluate call each, plus one initial call for problems without ``start``).
        lambdas: damping multipliers tried per iteration (each trial carries its Jacobian: n + 1 rows).
        damping: initial Marquardt lambda (scaling diag(J^T J)).
        tol_abs, tol_rel: a problem stops when an accepted step lowers the cost by less than
            tol_abs + tol_rel * cost (half chi-square units), when the undamped Gauss-Newton step predicts less
            than that, or after two successive iterations in which no trial lowered it.
        start: optional already evaluated start (residual, Jacobian, payload) per problem.
        on_iteration: callback(iteration, costs) for progress logging.
    """
    start = list(start) if start is not None else [None] * len(problems)
    states: list[FitResult | None] = list(start)
    need = [j for j, s in enumerate(states) if s is None]
    if need:
        probes = [probe_rows(problems[j].x0, problems[j]) for j in need]
        outs = evaluate([(j, p) for j, (p, _) in zip(need, probes, strict=True)])
        for j, (res, payload), (_, h) in zip(need, outs, probes, strict=True):
            r, jac = jacobian(res.to(torch.float64), h)
            states[j] = _state(problems[j], problems[j].x0, r, jac, payload[0])
    lam = [damping] * len(problems)
    failures = [0] * len(problems)
    active = list(range(len(problems)))
    for it in range(1, max_iter + 1):
        if not active:
            break
        trials: dict[int, list[tuple[torch.Tensor, torch.Tensor, float]]] = {}
        batch: list[tuple[int, torch.Tensor]] = []
        for j in list(active):
            st, pb = states[j], problems[j]
            r, jac = pb.augment(st.residual, st.jacobian, st.x)
            g, a = jac.T @ r, jac.T @ jac
            # The undamped Gauss-Newton step predicts a decrease of 0.5 g^T A^-1 g: too small, done.
            if 0.5 * float(g @ (torch.linalg.pinv(a) @ g)) < tol_abs + tol_rel * st.cost:
                st.converged = True
                active.remove(j)
                continue
            diag = torch.diag(a).clamp(min=1e-12 * float(torch.diag(a).max().clamp(min=1e-300)))
            trials[j] = []
            for mult in lambdas:
                lm = lam[j] * mult
                dx = torch.linalg.solve(a + lm * torch.diag(diag), -g)
                xt = torch.minimum(torch.maximum(st.x + dx, pb.lower), pb.upper)
                rows, h = probe_rows(xt, pb)
                trials[j].append((xt, h, lm))
                batch.append((j, rows))
        if not batch:
            break
        outs = evaluate(batch)
        pos = 0
        still = []
        for j in active:
            st, pb = states[j], problems[j]
            best = None
            for xt, h, lm in trials[j]:
                res, payload = outs[pos]
                pos += 1
                r, jac = jacobian(res.to(torch.float64), h)
                cand = _state(pb, xt, r, jac, payload[0])
                if best is None or cand.cost < best[0].cost:
                    best = (cand, lm)
            st.history.append(st.cost)
            cand, lm = best
            if cand.cost < st.cost:
                gain = st.cost - cand.cost
                cand.history, cand.iterations = st.history, it
                states[j] = cand
                lam[j] = lm
                if gain < tol_abs + tol_rel * cand.cost:
                    cand.converged = True
                    continue
                failures[j] = 0
            else:
                # Every damping tried failed: retry once with much more damping, then stop (at the optimum
                # to within the finite-difference resolution).
                st.iterations = it
                lam[j] *= 100.0
                failures[j] += 1
                if failures[j] >= 2 or lam[j] > 1e10:
                    st.converged = True
                    continue
            still.append(j)
        active = still
        if on_iteration is not None:
            on_iteration(it, [s.cost for s in states])
    for s in states:
        s.history.append(s.cost)
    return states


def _state(problem: Problem, x: torch.Tensor, r: torch.Tensor, jac: torch.Tensor, payload: Any) -> FitResult:
    ra, _ = problem.augment(r, jac, x)
    return FitResult(x.clone(), r, jac, 0.5 * float(ra @ ra), payload=payload)
