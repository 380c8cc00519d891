"""Which effect is missing: a score (Lagrange-multiplier) test per library effect not in the model.

For a candidate effect with strength theta (0 = off), the fit loss 0.5 ||r||^2 of the calibrated model has
gradient u = S^T r at theta = 0, where S = dr/dtheta is the effect's *sensitivity signature*. All
signatures come from ONE batched simulator call: row j of the batch carries direction j (one candidate,
one strength parameter at a small value, its shape parameters at one point of a grid), every other
candidate at strength 0. The signatures are projected off the span of the free parameters' Jacobian J
(the efficient score: only what the calibration could not already absorb counts), then

    T = u^T V^-1 u  ~  chi2(q)  under "effect absent",

q the rank of the candidate's directions. V is the Newey-West (Bartlett, ``hac_window``) long-run variance of
the score contributions g_t = S_t e_t, e the residual once the candidate's own least-squares fit is removed
(the Wald form: a strong missing effect is not counted as noise against itself). It reduces to
sigma^2 S^T S for a white residual and stays valid when the residual carries other unmodelled, coloured
structure (another missing effect, LF-vs-HF model error); the smaller of the robust and the white-noise
statistics is used (Newey-West is noisy for signatures concentrated in few samples). A single direction of a strength that must be >= 0 is tested one-sided. Candidates are
ranked by p-value; ``significant`` uses a Bonferroni level alpha / K over the K candidates tested.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch
from scipy import special, stats

from .. import checks
from ..effects import EFFECTS
from ..params import ActuatorParams
from .calibrate import Calibration
from .model import Evaluator
from .parameters import effect_defaults


@dataclass(frozen=True)
class ScoreSettings:
    """Attributes:
    step: strength of the probe rows, as a fraction of the parameter's declared scale.
    hac_window: Bartlett window of the Newey-West variance [s] (200 samples at 20 kHz): the residual's
        correlation time is the loop's and the filter's, not the acquisition's.
    alpha: family-wise significance level (Bonferroni over the candidates tested).
    grid: {effect: {shape parameter: [values]}} probed besides the defaults (directions of the test); a
        parameter sized by the actuator (``EffectParam.per``: the Stribeck velocity, the current scales) is
        listed in multiples of its typical magnitude there ([0.4, 1, 3]: 2, 5 and 15 rad/s of Stribeck velocity
        on the reference's 300 rad/s speed limit), any other in its unit.
    alias_ratio: candidates whose signature keeps less than this fraction of its energy after projecting
        off the free parameters are reported as aliased (not testable with these free parameters).
    rank_tol: directions of a candidate whose information is below this fraction of its largest are
        dropped (grid points that span the same signatures); the test's dof is the rank kept.
    min_gain: practical significance: the share of the residual sum of squares a candidate must explain
        (one-step estimate here, the actual reduction once refitted). With tens of thousands of samples a
        test detects immaterial structure (e.g. LF-vs-HF model error); an unmodelled effect of RMS
        0.66 sigma, the size at which the NRMSE reaches 1.2x the noise floor, explains 30 %.
    data_orders: how many of the residual's strongest rotor-angle orders are proposed as the ``order`` of
        candidates that have one (``torque_ripple``), unless ``grid`` gives their orders.
    """

    step: float = 0.1
    hac_window: float = 0.01
    alpha: float = 0.01
    grid: Mapping[str, Mapping[str, Sequence[float]]] = field(default_factory=dict)
    alias_ratio: float = 1e-3
    rank_tol: float = 1e-3
    min_gain: float = 0.01
    data_orders: int = 3

    def __post_init__(self) -> None:
        step = checks.number(self.step, "score.step")
        if not (0 < step <= 10):
            raise ValueError(f"score.step must be in (0, 10] (fraction of the parameter scale), got {self.step!r}")
        alpha = checks.number(self.alpha, "score.alpha")
        if not 0 < alpha < 1:
            raise ValueError(f"score.alpha must be in (0, 1), got {self.alpha!r}")
        grid = {}
        for name, g in checks.mapping(self.grid, "score.grid").items():
            if name not in EFFECTS:
                raise ValueError(f"score.grid: unknown effect {name!r}; available: {sorted(EFFECTS)}")
            grid[name] = {}
            for key, vals in checks.mapping(g, f"score.grid.{name}").items():
                if key not in EFFECTS[name].PARAMS or key in EFFECTS[name].STRENGTH:
                    raise ValueError(f"score.grid.{name}.{key}: not a shape parameter of {name}")
                if not vals:
                    raise ValueError(f"score.grid.{name}.{key}: empty list of values")
                grid[name][key] = checks.numbers(vals, f"score.grid.{name}.{key}")
        values = {
            "step": step,
            "alpha": alpha,
            "grid": grid,
            "hac_window": checks.number(self.hac_window, "score.hac_window", 0.0),
            "alias_ratio": checks.number(self.alias_ratio, "score.alias_ratio", 0.0),
            "rank_tol": checks.number(self.rank_tol, "score.rank_tol", 0.0),
            "min_gain": checks.number(self.min_gain, "score.min_gain", 0.0),
            "data_orders": checks.integer(self.data_orders, "score.data_orders", 0),
        }
        if not values["min_gain"] < 1:
            raise ValueError(f"score.min_gain must be in [0, 1), got {self.min_gain!r}")
        for key, value in values.items():
            object.__setattr__(self, key, value)


@dataclass
class Direction:
    """One probe: effect ``effect`` with parameter values ``values`` (strength ``strength`` at ``step`` scales)."""

    effect: str
    strength: str
    values: dict[str, float]


@dataclass
class Candidate:
    """Score-test outcome of one library effect (refit fields filled in by the workbench).

    Attributes:
        effect: name.  score: the chi-square statistic T.  dof: q.  p_value, log10_p: its p-value.
        significant: p < alpha / K, not aliased, explains >= ``min_gain`` of the residual sum of squares; once
            refitted, the refit must also lower the BIC and the sum of squares by ``min_gain``.
        aliased_with: the free parameter the signature is confounded with, when aliased.
        explained_fraction: share of the residual sum of squares a linear step along the candidate removes.
        start: effect parameter values to start a refit (best grid point, one-step strength estimate).
        contribution: the best direction's one-step change of the normalised residual, (m,).
    """

    effect: str
    score: float
    dof: int
    p_value: float
    log10_p: float
    significant: bool = False
    aliased_with: str | None = None
    explained_fraction: float = 0.0
    start: dict[str, float] = field(default_factory=dict)
    contribution: torch.Tensor | None = None
    evidence: dict[str, Any] = field(default_factory=dict)
    refit: Calibration | None = None
    delta_bic: float | None = None


def directions(names: Sequence[str], settings: ScoreSettings, params: ActuatorParams) -> list[Direction]:
    """Probe directions of the candidates: every strength parameter x every grid point of shape parameters.

    Strengths are probed at ``step`` x their typical magnitude on the actuator ``params``; shape parameters
    sized by the actuator (``EffectParam.per``, e.g. a current scale) at that magnitude, the others at their
    defaults, unless the grid gives them (sized ones as multiples of that magnitude).
    """
    out = []
    for name in names:
        cls = EFFECTS[name]
        grid = settings.grid.get(name, {})
        keys = list(grid)
        unit = {k: cls.PARAMS[k].scale_for(params) if cls.PARAMS[k].per else 1.0 for k in keys}
        for combo in itertools.product(*[list(grid[k]) for k in keys]) if keys else [()]:
            base = effect_defaults(name, {k: v * unit[k] for k, v in zip(keys, combo)}, params)
            for s in cls.STRENGTH:
                vals = {
                    k: (settings.step * cls.PARAMS[k].scale_for(params) if k == s else 0.0) if k in cls.STRENGTH else v
                    for k, v in base.items()
                }
                out.append(Direction(name, s, vals))
    return out


def newey_west(g: np.ndarray, lags: int) -> np.ndarray:
    """Long-run covariance sum_k w_k Gamma_k of score contributions g (T, q), Bartlett weights 1 - k/(L+1)."""
    v = g.T @ g
    for k in range(1, min(lags, len(g) - 1) + 1):
        c = g[:-k].T @ g[k:]
        v += (1.0 - k / (lags + 1.0)) * (c + c.T)
    return v


def score_tests(
    cal: Calibration, names: Sequence[str], settings: ScoreSettings, given: Mapping[str, Sequence[str]] | None = None
) -> list[Candidate]:
    """Score-test every effect in ``names`` against the calibrated model (one simulator call).

    Args:
        given: {candidate: [other candidates]}: the candidate is tested for what it adds beyond the others'
            signatures (projected off them, as off the free parameters). A ``torque_ripple`` probed at an
            order next to the cogging order would otherwise borrow the cogging residual's leakage: over a
            partial rotor turn neighbouring orders are not orthogonal.
    Returns the candidates ranked by p-value (most significant first).
    """
    names = [n for n in names if n not in cal.space.effects]
    if not names:
        return []
    dirs = directions(names, settings, cal.space.params)
    ev: Evaluator = cal.evaluator
    x = cal.x.reshape(1, -1)
    blocks = [cal.space.with_effect(d.effect, d.values, [], cal.x, 1.0, label=d.effect) for d in dirs]
    outs = ev.simulate([(sp, x) for sp, _ in blocks])
    r = cal.result.residual
    sig = torch.stack([(ev.residuals(o, cal.sigma)[0] - r) / settings.step for o in outs], dim=1)  # (m, D)
    jac = cal.result.jacobian
    q_basis = torch.linalg.qr(jac).Q if jac.shape[1] else jac
    eff = sig - q_basis @ (q_basis.T @ sig) if jac.shape[1] else sig
    alpha_k = settings.alpha / len(names)
    cands = []
    for name in names:
        idx = [j for j, d in enumerate(dirs) if d.effect == name]
        e, res = eff[:, idx], r
        others = [j for j, d in enumerate(dirs) if d.effect in (given or {}).get(name, ()) and d.effect in names]
        if others:
            q = _span(eff[:, others], settings.rank_tol)
            e, res = e - q @ (q.T @ e), r - q @ (q.T @ r)
        cands.append(_test(name, [dirs[j] for j in idx], sig[:, idx], e, res, jac, cal, settings, float(r @ r)))
    for c in cands:
        c.significant = c.aliased_with is None and c.p_value < alpha_k and c.explained_fraction >= settings.min_gain
    cands.sort(key=lambda c: (c.log10_p, -c.score))
    return cands


def _span(s: torch.Tensor, tol: float) -> torch.Tensor:
    """Orthonormal basis (m, k) of the columns of s, directions below ``tol`` x the largest singular value dropped."""
    u, sv, _ = torch.linalg.svd(s, full_matrices=False)
    return u[:, sv > tol * sv.max()] if sv.numel() and float(sv.max()) > 0 else s[:, :0]


def _test(
    name: str,
    dirs: list[Direction],
    raw: torch.Tensor,
    eff: torch.Tensor,
    r: torch.Tensor,
    jac: torch.Tensor,
    cal: Calibration,
    settings: ScoreSettings,
    rr: float | None = None,
) -> Candidate:
    """One candidate's test; ``rr``: the residual sum of squares its explained fraction is a share of
    (default ``r @ r``; the full residual's when ``r`` is conditioned on other candidates)."""
    cls = EFFECTS[name]
    a = (eff.T @ eff).numpy()
    raw_energy = (raw * raw).sum(0).numpy()
    kept = np.diag(a) / np.maximum(raw_energy, 1e-300)
    if raw_energy.max() <= 0 or kept.max() < settings.alias_ratio:
        return Candidate(
            name, 0.0, 0, 1.0, 0.0, aliased_with=_aliases(raw[:, int(np.argmax(raw_energy))], jac, cal.space.names())
        )
    u = (eff.T @ r).numpy()
    w, vecs = np.linalg.eigh(a)
    keep = w > settings.rank_tol * w.max()
    basis = vecs[:, keep]
    # Newey-West variance of u from the per-sample contributions g_t = S_t r_t (channels summed at each time
    # of each record), r with the candidate's own least-squares fit removed: otherwise a strong missing
    # effect would count as coloured noise against itself.
    sb = eff @ torch.as_tensor(basis)
    coef = torch.linalg.lstsq(sb, r.unsqueeze(-1)).solution
    r_alt = r - (sb @ coef).squeeze(-1)
    v = np.zeros_like(a)
    parts = zip(cal.evaluator.records, cal.evaluator.split(eff.T), cal.evaluator.split(r_alt), strict=True)
    for rec, part_e, part_r in parts:
        g = sum(part_e[c].numpy().T * part_r[c].numpy()[:, None] for c in part_e)
        v += newey_west(np.asarray(g), round(settings.hac_window * rec.sample_rate))
    # The robust variance never below the white-noise one: Newey-West is noisy for signatures concentrated in
    # few samples (e.g. at current zero crossings) and could understate it.
    s2 = float(r_alt @ r_alt) / max(len(r_alt) - jac.shape[1] - basis.shape[1], 1)
    ub = basis.T @ u
    stat, vb = min(((_quad(ub, m), m) for m in (basis.T @ v @ basis, s2 * (basis.T @ a @ basis))), key=lambda t: t[0])
    dof = int(keep.sum())
    # one-step estimate along each single direction: theta_j = -u_j / a_jj (residual change theta * eff_j)
    theta = -u / np.maximum(np.diag(a), 1e-300)
    minimum = [cls.PARAMS[d.strength].minimum for d in dirs]
    gain = np.where([(mn is not None and mn >= 0 and t < 0) for mn, t in zip(minimum, theta)], 0.0, u**2 / np.diag(a))
    best = int(np.argmax(gain))
    one_sided = len(dirs) == 1 and minimum[0] is not None and minimum[0] >= 0
    if one_sided:
        z = float(-ub[0] / math.sqrt(max(vb[0, 0], 1e-300))) * float(np.sign(basis[0, 0]))
        stat = z * abs(z)
        log_p = float(stats.norm.logsf(z))
    else:
        log_p = chi2_logsf(stat, dof)
    rr = float(r @ r) if rr is None else rr
    explained = float(u @ np.linalg.pinv(a, rcond=1e-10, hermitian=True) @ u) / rr if rr > 0 else 0.0
    d = dirs[best]
    start = dict(d.values)
    magnitude = cls.PARAMS[d.strength].scale_for(cal.space.params)  # the probe's unit: theta is in it
    start[d.strength] = max(float(theta[best]), 0.0 if minimum[best] is not None else -math.inf) * magnitude
    if minimum[best] is not None:
        start[d.strength] = max(start[d.strength], minimum[best])
    contribution = float(theta[best]) * eff[:, best] if gain[best] > 0 else torch.zeros_like(r)
    return Candidate(
        name,
        stat,
        dof,
        math.exp(log_p),
        log_p / math.log(10.0),
        explained_fraction=explained,
        start=start,
        contribution=contribution,
    )


def _quad(u: np.ndarray, v: np.ndarray) -> float:
    """u^T V^+ u."""
    return float(u @ np.linalg.pinv(v, rcond=1e-10, hermitian=True) @ u)


def chi2_logsf(x: float, dof: int) -> float:
    """log P(chi2(dof) > x), finite far in the tail (leading term of the upper incomplete gamma function)."""
    v = float(stats.chi2.logsf(x, dof))
    if math.isfinite(v):
        return v
    k = 0.5 * dof
    return (k - 1.0) * math.log(0.5 * x) - 0.5 * x - float(special.gammaln(k))


def _aliases(sig: torch.Tensor, jac: torch.Tensor, names: list[str]) -> str:
    """The free parameters whose columns rebuild a signature (each carrying >= 10 % of the fit)."""
    if not jac.shape[1] or float(sig.norm()) == 0.0:
        return "nothing (no signature)"
    coef = torch.linalg.lstsq(jac, sig.unsqueeze(-1)).solution.squeeze(-1)
    part = (coef * jac.norm(dim=0)).abs()
    keep = [n for n, v in zip(names, part.tolist(), strict=True) if v >= 0.1 * float(part.max())]
    return ", ".join(keep)
