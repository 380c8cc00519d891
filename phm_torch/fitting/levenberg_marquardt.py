"""Bounded Levenberg-Marquardt with forward-difference Jacobians, for batched simulators.

The one solver of the project's parameter fits (the workbench's calibrations and refits, the LF shape fit).
Several independent problems share each simulator call: every call carries the rows of all problems still
running (e.g. the refits of the top candidates), and a batched simulation costs little more for more rows.
Each iteration proposes one clipped step per damping multiplier and keeps the best; the damping scales
diag(J^T J) (Marquardt). Forward differences step backwards at an upper bound, so every probe is feasible.

Two ways to spend rows per iteration (``trial_jacobians``):

* ``True`` (the workbench): every trial is evaluated together with its Jacobian, trials x (n + 1) rows; the
  best trial is accepted with its Jacobian known: one call per iteration. Cheapest when a call costs about
  the same for 10 or 100 rows (short records, per-call overhead dominates).
* ``False`` (the LF fit): the trials alone (one row each), then the Jacobian at the accepted point (n + 1
  rows): two calls per accepted iteration, fewest rows. Cheapest when the cost grows with the rows (each
  row is a batch of long records).

Residuals should be normalised (divided by the noise standard deviation or a scale), so the cost
0.5 ||r||^2 is half a chi-square and the Gauss-Newton (Laplace) covariance is s^2 (J^T J)^-1 with
s^2 = ||r||^2 / (m - n).
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
            raise ValueError(
                f"start value x0[{bad}] = {float(self.x0[bad]):.6g} is outside its bounds "
                f"[{float(self.lower[bad]):.6g}, {float(self.upper[bad]):.6g}]"
            )

    def augment(self, r: torch.Tensor, jac: torch.Tensor, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Residual and Jacobian with the prior rows appended."""
        if self.prior_weight is None:
            return r, jac
        mean = self.prior_mean if self.prior_mean is not None else torch.zeros_like(x)
        return (torch.cat([r, self.prior_weight * (x - mean)]), torch.cat([jac, torch.diag(self.prior_weight)]))

    def cost(self, r: torch.Tensor, x: torch.Tensor) -> float:
        """0.5 ||r||^2 of the residual r (m,) at x, prior rows included."""
        if self.prior_weight is not None:
            mean = self.prior_mean if self.prior_mean is not None else torch.zeros_like(x)
            r = torch.cat([r, self.prior_weight * (x - mean)])
        return 0.5 * float(r @ r)


@dataclass
class FitResult:
    """Outcome of one fit.

    Attributes:
        x: (n,).  residual: r(x) (m,), prior excluded.  jacobian: dr/dx (m, n).  cost: 0.5 ||r||^2 (prior
        included).  iterations, converged, history (cost before each iteration, then the final cost).
        payload: evaluate's data of x.
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
        """Gauss-Newton/Laplace covariance s^2 (J^T J + prior)^-1 of x (n, n), s^2 = ||r||^2 / (m - n)."""
        m, n = self.jacobian.shape
        s2 = self.chi2 / max(m - n, 1)
        a = self.jacobian.T @ self.jacobian
        if problem is not None and problem.prior_weight is not None:
            a = a + torch.diag(problem.prior_weight**2)
        return s2 * torch.linalg.pinv(a)

    def std(self, problem: Problem | None = None) -> torch.Tensor:
        """Standard deviation of x (n,): square root of the covariance's diagonal."""
        return self.covariance(problem).diagonal().clamp(min=0.0).sqrt()


def probe_rows(x: torch.Tensor, problem: Problem) -> tuple[torch.Tensor, torch.Tensor]:
    """[x; x + h_i e_i] (n + 1, n) and the signed steps h (n,) (backwards at an upper bound)."""
    h = torch.where(x + problem.step > problem.upper, -problem.step, problem.step)
    return torch.cat([x.unsqueeze(0), x.unsqueeze(0) + torch.diag(h)]), h


def jacobian(res: torch.Tensor, h: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Residual r (m,) and forward-difference Jacobian (m, n) from probe residuals (n + 1, m)."""
    r = res[0]
    return r, ((res[1:] - r) / h.unsqueeze(-1)).T


def from_residuals(residuals: Callable[[torch.Tensor], torch.Tensor]) -> Evaluate:
    """An :data:`Evaluate` from a batched residual function (P, n) -> (P, m) shared by every problem: the rows
    of all problems go through one call; the payload of every row is ``None``."""

    def evaluate(items: list[tuple[int, torch.Tensor]]) -> list[tuple[torch.Tensor, Any]]:
        res = residuals(torch.cat([x for _, x in items])).detach()
        return [(r, [None] * len(r)) for r in res.split([len(x) for _, x in items])]

    return evaluate


def fit(
    evaluate: Evaluate,
    problems: Sequence[Problem],
    max_iter: int = 8,
    lambdas: Sequence[float] = (0.1, 1.0, 10.0),
    damping: float = 1e-2,
    tol_abs: float = 0.5,
    tol_rel: float = 1e-4,
    start: Sequence[FitResult | None] | None = None,
    on_iteration: Callable[[int, list[float]], None] | None = None,
    *,
    trial_jacobians: bool = True,
    predicted_stop: bool = True,
    max_failures: int | None = 2,
    max_damping: float = 1e10,
) -> list[FitResult]:
    """Minimise 0.5 ||r_j(x)||^2 (+ prior) for every problem j within its bounds, sharing evaluate calls.

    Args:
        evaluate: see :data:`Evaluate` (:func:`from_residuals` wraps a plain batched residual function).
        problems: the fits.
        max_iter: iterations (one trial call each, plus one Jacobian call after an accepted step when
            ``trial_jacobians`` is false, plus one initial call for problems without ``start``).
        lambdas: damping multipliers tried per iteration.
        damping: initial Marquardt lambda (scaling diag(J^T J)); the accepted trial's lambda carries on.
        tol_abs, tol_rel: a problem stops when an accepted step lowers the cost by less than
            tol_abs + tol_rel * cost (half chi-square units, cost after the step).
        start: optional already evaluated start (residual, Jacobian, payload) per problem.
        on_iteration: callback(iteration, costs) for progress logging.
        trial_jacobians: evaluate each trial with its Jacobian (module docstring).
        predicted_stop: also stop when the undamped Gauss-Newton step predicts a decrease below that
            tolerance (saves the iteration that would confirm it).
        max_failures: when no trial lowers the cost, the damping grows 100-fold and the problem stops after
            this many successive such iterations (``None``: no limit) ...
        max_damping: ... or once the damping exceeds this (at the optimum to within the finite-difference
            resolution).
    """
    start = list(start) if start is not None else [None] * len(problems)
    states: list[FitResult | None] = list(start)
    need = {j: problems[j].x0 for j, s in enumerate(states) if s is None}
    for j, st in (_at(evaluate, problems, need) if need else {}).items():
        states[j] = st
    lam = [damping] * len(problems)
    failures = [0] * len(problems)
    active = list(range(len(problems)))
    for it in range(1, max_iter + 1):
        if not active:
            break
        trials: dict[int, list[tuple[torch.Tensor, torch.Tensor | None, float]]] = {}
        batch: list[tuple[int, torch.Tensor]] = []
        for j in list(active):
            st, pb = states[j], problems[j]
            r, jac = pb.augment(st.residual, st.jacobian, st.x)
            g, a = jac.T @ r, jac.T @ jac
            # The undamped Gauss-Newton step predicts a decrease of 0.5 g^T A^-1 g: too small, done.
            if predicted_stop and 0.5 * float(g @ (torch.linalg.pinv(a) @ g)) < tol_abs + tol_rel * st.cost:
                st.converged = True
                active.remove(j)
                continue
            diag = torch.diag(a).clamp(min=1e-12 * float(torch.diag(a).max().clamp(min=1e-300)))
            trials[j] = []
            for mult in lambdas:
                lm = lam[j] * mult
                dx = torch.linalg.solve(a + lm * torch.diag(diag), -g)
                xt = torch.minimum(torch.maximum(st.x + dx, pb.lower), pb.upper)
                rows, h = probe_rows(xt, pb) if trial_jacobians else (xt.unsqueeze(0), None)
                trials[j].append((xt, h, lm))
                batch.append((j, rows))
        if not batch:
            break
        outs = evaluate(batch)
        pos = 0
        still = []
        accepted: dict[int, tuple[torch.Tensor, bool]] = {}
        for j in active:
            st, pb = states[j], problems[j]
            best = None
            for xt, h, lm in trials[j]:
                res, payload = outs[pos]
                pos += 1
                res = res.to(torch.float64)
                if h is None:
                    cost, full = pb.cost(res[0], xt), None
                else:
                    full = _state(pb, xt, *jacobian(res, h), payload[0])
                    cost = full.cost
                if best is None or cost < best[0]:
                    best = (cost, xt, full, lm)
            st.history.append(st.cost)
            cost, xt, full, lm = best
            if cost < st.cost:
                done = st.cost - cost < tol_abs + tol_rel * cost
                if full is None:  # its Jacobian: one call for every accepted problem, after this loop
                    accepted[j] = (xt, done)
                else:
                    full.history, full.iterations, full.converged = st.history, it, done
                    states[j] = full
                lam[j] = lm
                if done:
                    continue
                failures[j] = 0
            else:
                # Every damping tried failed: retry with much more damping, then stop.
                st.iterations = it
                lam[j] *= 100.0
                failures[j] += 1
                if (max_failures is not None and failures[j] >= max_failures) or lam[j] > max_damping:
                    st.converged = True
                    continue
            still.append(j)
        if accepted:
            for j, new in _at(evaluate, problems, {j: x for j, (x, _) in accepted.items()}).items():
                new.history, new.iterations, new.converged = states[j].history, it, accepted[j][1]
                states[j] = new
        active = still
        if on_iteration is not None:
            on_iteration(it, [s.cost for s in states])
    for s in states:
        s.history.append(s.cost)
    return states


def _at(evaluate: Evaluate, problems: Sequence[Problem], points: dict[int, torch.Tensor]) -> dict[int, FitResult]:
    """Residual, Jacobian and payload at points[j] of problems j, in one evaluate call."""
    probes = {j: probe_rows(x, problems[j]) for j, x in points.items()}
    outs = evaluate([(j, rows) for j, (rows, _) in probes.items()])
    states = {}
    for (j, (_, h)), (res, payload) in zip(probes.items(), outs, strict=True):
        r, jac = jacobian(res.to(torch.float64), h)
        states[j] = _state(problems[j], points[j], r, jac, payload[0])
    return states


def _state(problem: Problem, x: torch.Tensor, r: torch.Tensor, jac: torch.Tensor, payload: Any) -> FitResult:
    return FitResult(x.clone(), r, jac, problem.cost(r, x), payload=payload)
