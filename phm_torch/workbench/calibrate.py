"""Calibration: fit the free parameters of one or several models to the records, with uncertainty.

The residual of a model is (simulated - measured) / sigma over every record and compared channel, sigma
being the channel's noise standard deviation estimated from the high band of the residual at the start
point (:class:`~phm_torch.workbench.noise.HighBandNoise`). Several models (e.g. the refits of the top
candidates) are fitted together, one shared simulator call per Levenberg-Marquardt iteration.
"""

from __future__ import annotations

import inspect
import logging
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch

from .. import checks
from ..fitting import FitResult, Problem, fit
from .model import Evaluator
from .parameters import ParameterSpace

log = logging.getLogger(__name__)
MIN_RELATIVE_NOISE = 1e-6  # sigma floor as a fraction of the channel range (noise-free data)
_LM = inspect.signature(fit).parameters  # FitSettings' defaults: the solver's own (phm_torch.fitting.fit)


@dataclass(frozen=True)
class FitSettings:
    """Levenberg-Marquardt settings (one batched simulator call per iteration); the defaults are
    :func:`phm_torch.fitting.fit`'s.

    Attributes:
        max_iter: iterations.
        lambdas: damping multipliers tried per iteration, each trial with its Jacobian.
        damping: initial Marquardt lambda.
        tol_abs, tol_rel: stop when an accepted step gains less than tol_abs + tol_rel * cost (cost = chi^2 / 2
            of the noise-normalised residual).
    """

    max_iter: int = _LM["max_iter"].default
    lambdas: tuple[float, ...] = _LM["lambdas"].default
    damping: float = _LM["damping"].default
    tol_abs: float = _LM["tol_abs"].default
    tol_rel: float = _LM["tol_rel"].default

    def __post_init__(self) -> None:
        values = {
            "max_iter": checks.integer(self.max_iter, "max_iter", 1),
            "lambdas": checks.numbers(self.lambdas, "lambdas", 0.0, True),
            "damping": checks.number(self.damping, "damping", 0.0, True),
            "tol_abs": checks.number(self.tol_abs, "tol_abs", 0.0),
            "tol_rel": checks.number(self.tol_rel, "tol_rel", 0.0),
        }
        for key, value in values.items():
            object.__setattr__(self, key, value)


@dataclass
class Calibration:
    """A fitted model.

    Attributes:
        space: the model and its free parameters.  result: the fit at its optimum.  problem: bounds/prior.
        sigma: per record {channel: noise std used to normalise} [channel unit].
        simulated: per record {channel: (n,)} simulated at the optimum (states included).
        evaluator: the records and compared channels.
    """

    space: ParameterSpace
    result: FitResult
    problem: Problem
    sigma: list[dict[str, float]]
    simulated: list[dict[str, torch.Tensor]]
    evaluator: Evaluator

    @property
    def x(self) -> torch.Tensor:
        return self.result.x

    @property
    def label(self) -> str:
        return self.space.label

    @property
    def chi2(self) -> float:
        return self.result.chi2

    @property
    def bic(self) -> float:
        """chi^2 + k ln(m): Bayesian information criterion with the noise variance known (up to a constant)."""
        return self.chi2 + self.space.n * math.log(self.evaluator.m)

    def std_x(self) -> torch.Tensor:
        """Laplace standard deviations of the normalised parameters (n,)."""
        return self.result.std(self.problem)

    def fitted(self) -> dict[str, tuple[float, float]]:
        """{parameter: (value, std)} in reported units."""
        return self.space.fitted(self.x, self.std_x())

    def errors(self) -> list[dict[str, np.ndarray]]:
        """Per record {channel: simulated - measured (n,)} in channel units."""
        return [
            {c: (self.simulated[i][c] - rec.measured[c]).numpy() for c in self.evaluator.channels}
            for i, rec in enumerate(self.evaluator.records)
        ]

    def normalised(self) -> list[dict[str, np.ndarray]]:
        """Per record {channel: (simulated - measured) / sigma}."""
        return [{c: e[c] / self.sigma[i][c] for c in e} for i, e in enumerate(self.errors())]


def estimate_sigma(
    evaluator: Evaluator, simulated: Sequence[dict[str, torch.Tensor]], noise: Callable[[np.ndarray, float], float]
) -> list[dict[str, float]]:
    """Noise std per record and channel from the residual's high band (floored at 1e-6 of the range)."""
    out = []
    for i, rec in enumerate(evaluator.records):
        d = {}
        for c in evaluator.channels:
            err = (simulated[i][c] - rec.measured[c]).numpy()
            d[c] = max(noise(err, rec.sample_rate), MIN_RELATIVE_NOISE * rec.channel_range(c))
        out.append(d)
    return out


def problem_of(space: ParameterSpace, x0: torch.Tensor | None = None, prior: torch.Tensor | None = None) -> Problem:
    x = space.vector("x0") if x0 is None else x0
    lo, hi = space.vector("lower"), space.vector("upper")
    return Problem(torch.minimum(torch.maximum(x, lo), hi), lo, hi, space.vector("step"), prior)


def fit_models(
    evaluator: Evaluator,
    spaces: Sequence[ParameterSpace],
    starts: Sequence[torch.Tensor | None],
    sigma: Sequence[dict[str, float]] | None,
    noise: Callable[[np.ndarray, float], float],
    settings: FitSettings,
    priors: Sequence[torch.Tensor | None] | None = None,
    on_iteration: Callable[[int, list[float]], None] | None = None,
) -> list[Calibration]:
    """Fit several models together (one simulator call per iteration for all of them).

    Args:
        spaces: the models.  starts: start vectors (``None``: the spaces' x0).
        sigma: noise std per record/channel; ``None`` estimates it from the residual of the first model at
            its start (then shared by all models, so that their chi^2 compare).
        priors: optional ridge weights (n_j,) per model (residual rows w * x).
    """
    priors = list(priors) if priors is not None else [None] * len(spaces)
    problems = [problem_of(s, x, p) for s, x, p in zip(spaces, starts, priors, strict=True)]
    state: dict[str, Any] = {"sigma": sigma}

    def evaluate(items: list[tuple[int, torch.Tensor]]) -> list[tuple[torch.Tensor, Any]]:
        outs = evaluator.simulate([(spaces[j], x) for j, x in items])
        if state["sigma"] is None:
            state["sigma"] = estimate_sigma(evaluator, outs[0].row(0), noise)
        return [(evaluator.residuals(o, state["sigma"]), _Rows(o)) for o in outs]

    results = fit(
        evaluate,
        problems,
        settings.max_iter,
        settings.lambdas,
        settings.damping,
        settings.tol_abs,
        settings.tol_rel,
        on_iteration=on_iteration,
    )
    return [
        Calibration(s, r, p, state["sigma"], r.payload, evaluator)
        for s, r, p in zip(spaces, results, problems, strict=True)
    ]


class _Rows:
    """Lazy per-row view of a :class:`BlockOutput` (payload of the fit)."""

    def __init__(self, out: Any):
        self.out = out

    def __getitem__(self, i: int) -> list[dict[str, torch.Tensor]]:
        return self.out.row(i)
