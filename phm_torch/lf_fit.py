"""Fit the LF shape coefficients to the HF model, validate on held-out vectors, keep or reject the fit.

Procedure (``phm-fit-lf``, :func:`run_fit`):

1. Fault vectors (:func:`fault_sets`): a *design* set (the nominal vector, then half importance-sampled
   as the training data are, half uniform on [0, 1]^8) and two held-out sets drawn from independent
   seed streams: ``importance`` (the seed paper's scaled Latin hypercube about nominal, k7 uniform) and
   ``uniform`` (Latin hypercube on [0, 1]^8).
2. One batched HF simulation of all of them on the command (the cost of the procedure).
3. :func:`fit_shape`: the coefficients (a_k, a_R, a_L, commutation width) that minimise
   sum over design vectors and channels of NRMSE^2 (LF - HF, RMS over the record divided by the HF
   range of that vector and channel), with the project's bounded Levenberg-Marquardt
   (:func:`~phm_torch.fitting.fit`, one LF call per Jacobian), inside physical
   bounds (:data:`PHYSICAL_BOUNDS`), starting from the physical values.
4. :func:`discrepancy` on both held-out sets with the physical values (``LFShape()``: 1, 1, 2, 0) and the
   fitted ones, and :func:`decide`.

The decision rule (keep the fit only if it improves every held-out set and worsens none) lives in
:mod:`phm_torch.lf_fit_decision`.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import asdict, dataclass, field, fields

import numpy as np
import torch
from scipy.stats import qmc

from .data.sampling import ImportanceSampler
from .faults import N_FAULTS
from .fitting import Problem, fit, from_residuals
from .lf_fit_decision import CHANNELS, Decision, decide
from .params import ActuatorParams, LFShape
from .simulator import EMASimulator

COEFFICIENTS = tuple(f.name for f in fields(LFShape))
HELD_OUT = ("importance", "uniform")
JITTER = 1e-3  # a change of every coefficient that no fit resolves (see ``fit_and_validate``)
# Physical ranges of the coefficients: EMF and resistance fall with the shorted fraction s at a rate
# near 1 (a_k, a_R = 1 +- 0.5: the short takes turns out of both); the inductance of a winding goes
# with the square of its turns (a_L = 2, between linear and cubic); the HF commutation transient lasts
# a few PWM periods, a small fraction of a 60-degree sector at the speeds of a position test, so a
# blend wider than 0.25 rad (electrical) fits the commutation ripple, not the commutation.
PHYSICAL_BOUNDS: dict[str, tuple[float, float]] = {
    "emf_short_gain": (0.5, 1.5),
    "resistance_short_gain": (0.5, 1.5),
    "inductance_short_exponent": (1.0, 3.0),
    "commutation_width": (0.0, 0.25),
}


@dataclass(frozen=True)
class LFFitSettings:
    """Sizes and rules of the LF shape fit (the ``fit`` node of ``conf/fit_lf.yaml``).

    Attributes:
        n_design: fault vectors the coefficients are fitted on (the nominal one included), >= 2.
        n_importance, n_uniform: held-out vectors, importance-sampled / uniform, each >= 1.
        max_iter: Levenberg-Marquardt iterations (each: two batched LF simulations), >= 1.
        seed: seeds the Latin hypercubes (four independent streams: two design halves, two held-out sets).
        duration: simulated record [s] (a prefix of the command); ``None``: the command's duration.
        bounds: {coefficient: [low, high]} overriding :data:`PHYSICAL_BOUNDS`.
        fd_step: forward-difference step of the coefficients (absolute): large enough to step over the
            jitter of the cost (vectors whose current loop rings respond chaotically to any change; with
            1e-3 the fit moved the coefficients by 5e-4 and "explained" noise).
        min_gain: relative fall of the held-out median current NRMSE required on both sets, in [0, 1).
        max_worsening: relative growth tolerated in any held-out median or max NRMSE, >= 0.
        outlier_factor: design vectors whose current NRMSE with the physical coefficients exceeds this
            multiple of the design median are left out of the fit (> 1; ``None``: keep all). Where a short
            makes the current loop ring, LF and HF part ways whatever the coefficients, and least squares
            would bend the coefficients towards those few vectors at the expense of all the others.
    """

    n_design: int
    n_importance: int
    n_uniform: int
    max_iter: int
    seed: int
    duration: float | None = None
    bounds: Mapping[str, Sequence[float]] = field(default_factory=dict)
    fd_step: float = 0.02
    min_gain: float = 0.02
    max_worsening: float = 0.0
    outlier_factor: float | None = 3.0

    def __post_init__(self) -> None:
        for name, low in (("n_design", 2), ("n_importance", 1), ("n_uniform", 1), ("max_iter", 1), ("seed", 0)):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int) or v < low:
                raise ValueError(f"fit.{name} must be an integer >= {low}, got {v!r}")
        if self.duration is not None and not _positive(self.duration):
            raise ValueError(f"fit.duration must be > 0 (or null for the command's duration), got {self.duration!r}")
        if not _positive(self.fd_step):
            raise ValueError(f"fit.fd_step must be > 0, got {self.fd_step!r}")
        if not (_number(self.min_gain) and 0.0 <= self.min_gain < 1.0):
            raise ValueError(f"fit.min_gain must be in [0, 1), got {self.min_gain!r}")
        if not (_number(self.max_worsening) and self.max_worsening >= 0.0):
            raise ValueError(f"fit.max_worsening must be >= 0, got {self.max_worsening!r}")
        if self.outlier_factor is not None and not (_number(self.outlier_factor) and self.outlier_factor > 1.0):
            raise ValueError(f"fit.outlier_factor must be > 1 (or null), got {self.outlier_factor!r}")
        bounds = dict(PHYSICAL_BOUNDS)
        for name, pair in dict(self.bounds or {}).items():
            if name not in PHYSICAL_BOUNDS:
                raise ValueError(f"fit.bounds: unknown coefficient {name!r}; known: {list(COEFFICIENTS)}")
            pair = list(pair) if isinstance(pair, Sequence) and not isinstance(pair, str) else [pair]
            if len(pair) != 2 or not all(_number(v) for v in pair) or not 0.0 <= pair[0] < pair[1]:
                raise ValueError(f"fit.bounds.{name} must be [low, high] with 0 <= low < high, got {pair!r}")
            bounds[name] = (float(pair[0]), float(pair[1]))
        physical = asdict(LFShape())
        for name, (lo, hi) in bounds.items():
            if not lo <= physical[name] <= hi:
                raise ValueError(f"fit.bounds.{name} = [{lo}, {hi}] must contain the physical value {physical[name]}")
        object.__setattr__(self, "bounds", bounds)


def _number(v: object) -> bool:
    return not isinstance(v, bool) and isinstance(v, (int, float)) and math.isfinite(v)


def _positive(v: object) -> bool:
    return _number(v) and v > 0


# ---- fault vectors -------------------------------------------------------------------------------
def uniform_faults(n: int, seed: np.random.SeedSequence | int) -> np.ndarray:
    """n fault vectors (n, 8) from a Latin hypercube on [0, 1]^8 (the whole domain)."""
    return qmc.LatinHypercube(d=N_FAULTS, rng=np.random.default_rng(seed)).random(n)


def fault_sets(params: ActuatorParams, settings: LFFitSettings) -> dict[str, torch.Tensor]:
    """The design set and the two held-out sets, float64 (n, 8) each, deterministic in ``settings.seed``.

    The design set is the nominal vector, ceil((n_design - 1) / 2) importance-sampled vectors and the rest
    uniform; every set has its own seed stream, so the held-out sets share no vector with the design.
    """
    s_imp, s_uni, s_held_imp, s_held_uni = np.random.SeedSequence(settings.seed).spawn(4)
    sampler = ImportanceSampler(params.nominal_faults, uniform=(6,), radius=1.0)
    n_imp = math.ceil((settings.n_design - 1) / 2)
    parts = [np.asarray(params.nominal_faults)[None], sampler.sample(n_imp, s_imp)]
    if settings.n_design - 1 - n_imp > 0:
        parts.append(uniform_faults(settings.n_design - 1 - n_imp, s_uni))
    design = np.concatenate(parts)
    sets = {
        "design": design,
        "importance": sampler.sample(settings.n_importance, s_held_imp),
        "uniform": uniform_faults(settings.n_uniform, s_held_uni),
    }
    return {k: torch.as_tensor(v, dtype=torch.float64) for k, v in sets.items()}


# ---- simulation and discrepancy ------------------------------------------------------------------
def simulate(
    params: ActuatorParams,
    fidelity: str,
    faults: torch.Tensor,
    command,
    duration: float,
    shapes: torch.Tensor | None = None,
) -> torch.Tensor:
    """Channels ``CHANNELS`` of a batched run, (B, 2, T): envelope current [A] and position [rad].

    ``shapes`` (B, 4): LF shape coefficients per vector, in ``COEFFICIENTS`` order (LF only; default the
    coefficients of ``params``).
    """
    scales = None if shapes is None else {f"lf_{c}": shapes[:, i] for i, c in enumerate(COEFFICIENTS)}
    with torch.no_grad():
        sig = EMASimulator(params, fidelity).run(faults, command, duration, scales=scales, channels=list(CHANNELS))
    return torch.stack([sig[c] for c in CHANNELS], dim=1)


def discrepancy(model: torch.Tensor, reference: torch.Tensor) -> torch.Tensor:
    """NRMSE per vector and channel (B, 2): RMS(model - reference) over the record / range of reference."""
    span = (reference.amax(-1) - reference.amin(-1)).clamp(min=1e-12)
    return (model - reference).pow(2).mean(-1).sqrt() / span


def summarize(d: torch.Tensor) -> dict[str, dict[str, float]]:
    """{channel: {median, mean, max}} of per-vector NRMSE (B, 2), fractions."""
    return {
        c: {"median": float(d[:, i].median()), "mean": float(d[:, i].mean()), "max": float(d[:, i].max())}
        for i, c in enumerate(CHANNELS)
    }


def as_vector(shape: LFShape) -> torch.Tensor:
    return torch.tensor([getattr(shape, c) for c in COEFFICIENTS], dtype=torch.float64)


# ---- fit -----------------------------------------------------------------------------------------
@dataclass
class ShapeFit:
    """Outcome of :func:`fit_shape`: ``shape`` (fitted coefficients), ``std`` (Gauss-Newton standard
    deviation per coefficient; meaningless where ringing vectors make the cost jitter), ``cost_history`` (0.5 sum NRMSE^2 before each iteration), ``iterations``,
    ``converged``, ``at_bound`` (coefficients that ended on a bound), ``excluded`` (design rows left out
    of the fit as outliers, set by :func:`fit_and_validate`)."""

    shape: LFShape
    std: dict[str, float]
    cost_history: list[float]
    iterations: int
    converged: bool
    at_bound: list[str]
    excluded: list[int] = field(default_factory=list)


def fit_shape(
    params: ActuatorParams,
    faults: torch.Tensor,
    reference: torch.Tensor,
    command,
    duration: float,
    bounds: Mapping[str, Sequence[float]] | None = None,
    max_iter: int = 8,
    fd_step: float = 0.02,
    start: LFShape | None = None,
) -> ShapeFit:
    """Fit the LF shape coefficients so that LF reproduces ``reference`` (B, 2, T) of ``faults`` (B, 8).

    Residual: (LF - reference) / range(reference) / sqrt(T) per vector and channel, so the cost is
    0.5 sum NRMSE^2. Every Levenberg-Marquardt evaluation of P coefficient vectors is one LF run of P * B.
    """
    b = faults.shape[0]
    span = (reference.amax(-1) - reference.amin(-1)).clamp(min=1e-12).unsqueeze(-1)
    norm = math.sqrt(reference.shape[-1])

    def residuals(x: torch.Tensor) -> torch.Tensor:
        p = x.shape[0]
        out = simulate(params, "lf", faults.repeat(p, 1), command, duration, x.repeat_interleave(b, dim=0))
        return ((out.view(p, b, *reference.shape[1:]) - reference) / span / norm).reshape(p, -1)

    bounds = {**PHYSICAL_BOUNDS, **dict(bounds or {})}
    lo = torch.tensor([bounds[c][0] for c in COEFFICIENTS], dtype=torch.float64)
    hi = torch.tensor([bounds[c][1] for c in COEFFICIENTS], dtype=torch.float64)
    x0 = torch.minimum(torch.maximum(as_vector(start or LFShape()), lo), hi)
    # Each row is a batch of B long LF records, so the solver spends the fewest rows: trials alone, then the
    # Jacobian at the accepted point; it stops on the relative gain or on a damping no step survives.
    res = fit(
        from_residuals(residuals),
        [Problem(x0, lo, hi, torch.full_like(x0, fd_step))],
        max_iter,
        lambdas=(0.1, 1.0, 10.0, 100.0),
        damping=1e-3,
        tol_abs=0.0,
        tol_rel=1e-6,
        trial_jacobians=False,
        predicted_stop=False,
        max_failures=None,
        max_damping=1e8,
    )[0]
    std = res.std()
    span_x = hi - lo
    at_bound = [c for i, c in enumerate(COEFFICIENTS) if min(res.x[i] - lo[i], hi[i] - res.x[i]) < 1e-6 * span_x[i]]
    return ShapeFit(
        LFShape(**{c: float(v) for c, v in zip(COEFFICIENTS, res.x)}),
        {c: float(s) for c, s in zip(COEFFICIENTS, std)},
        res.history[:-1],
        res.iterations,
        res.converged,
        at_bound,
    )


# ---- whole procedure -----------------------------------------------------------------------------
@dataclass
class LFFitResult:
    """Outcome of :func:`run_fit` / :func:`fit_and_validate`.

    Attributes:
        shape: the coefficients to use (fitted or physical, per ``decision``).
        fit: the Levenberg-Marquardt outcome.  decision: which was kept and why.
        summary: {set: {"physical" | "fitted" | "jitter" (| "input"): {channel: {median, mean, max}}}} for
            the design and held-out sets, NRMSE fractions ("jitter": the physical values + ``JITTER``, the
            noise floor of the comparison; "input": the actuator's own coefficients, when not physical).
        per_vector: {set: {"faults", "physical", "fitted"}} (lists, (n, 8) and (n, 2)).
    """

    shape: LFShape
    fit: ShapeFit
    decision: Decision
    summary: dict
    per_vector: dict


def fit_and_validate(
    params: ActuatorParams,
    command,
    duration: float,
    sets: Mapping[str, torch.Tensor],
    references: Mapping[str, torch.Tensor],
    settings: LFFitSettings,
) -> LFFitResult:
    """Fit on ``sets["design"]`` against ``references["design"]``, validate on the held-out sets, decide.

    ``references[name]`` (n, 2, T) are the target signals of ``sets[name]`` (the HF runs; tests may pass
    other targets). The physical and fitted LF runs of every set are one batched LF call.
    """
    physical = LFShape()
    design, reference = sets["design"], references["design"]
    inliers = torch.arange(design.shape[0])
    if settings.outlier_factor is not None:
        shapes = as_vector(physical).expand(design.shape[0], -1)
        d = discrepancy(simulate(params, "lf", design, command, duration, shapes), reference)[:, 0]
        inliers = torch.nonzero(d <= settings.outlier_factor * d.median()).flatten()
    fit = fit_shape(
        params,
        design[inliers],
        reference[inliers],
        command,
        duration,
        settings.bounds,
        settings.max_iter,
        settings.fd_step,
        start=physical,
    )
    fit.excluded = sorted(set(range(design.shape[0])) - set(inliers.tolist()))
    names = list(sets)
    # "jitter": the physical values moved by JITTER, far below what a fit resolves; how much the held-out
    # NRMSE moves with it is the noise floor of any before/after comparison (ringing vectors).
    jitter = LFShape(**{c: v + JITTER for c, v in asdict(physical).items()})
    candidates = {"physical": physical, "fitted": fit.shape, "jitter": jitter}
    if params.lf_shape != physical:
        candidates["input"] = params.lf_shape
    faults = torch.cat([sets[n] for n in names])
    k_all = faults.repeat(len(candidates), 1)
    shapes = torch.cat([as_vector(s).expand(faults.shape[0], -1) for s in candidates.values()])
    runs = simulate(params, "lf", k_all, command, duration, shapes).split(faults.shape[0])
    summary, per_vector = {n: {} for n in names}, {n: {"faults": sets[n].tolist()} for n in names}
    for label, run in zip(candidates, runs):
        for n, part in zip(names, run.split([sets[n].shape[0] for n in names])):
            d = discrepancy(part, references[n])
            summary[n][label] = summarize(d)
            per_vector[n][label] = d.tolist()
    held = [n for n in names if n != "design"]
    decision = decide(
        {n: summary[n]["physical"] for n in held},
        {n: summary[n]["fitted"] for n in held},
        settings.min_gain,
        settings.max_worsening,
    )
    return LFFitResult(fit.shape if decision.accepted else physical, fit, decision, summary, per_vector)


def run_fit(params: ActuatorParams, command, settings: LFFitSettings) -> LFFitResult:
    """The whole procedure: sample the sets, one batched HF run of all of them, fit, validate, decide."""
    duration = settings.duration if settings.duration is not None else getattr(command, "duration", None)
    if duration is None:
        raise ValueError("fit.duration is required when the command has no duration")
    periods = duration * params.pwm_frequency
    if round(periods) < 1 or abs(periods - round(periods)) > 1e-6:
        raise ValueError(
            f"fit.duration must be a positive whole number of control periods "
            f"(1/{params.pwm_frequency:g} s), got {duration!r}"
        )
    sets = fault_sets(params, settings)
    names = list(sets)
    hf = simulate(params, "hf", torch.cat([sets[n] for n in names]), command, duration)
    references = dict(zip(names, hf.split([sets[n].shape[0] for n in names])))
    return fit_and_validate(params, command, duration, sets, references, settings)
