"""Neural closure: a small MLP of the state added to the torque (or voltage) equation, fitted through the
simulator, for a residual that no library effect explains.

Inputs (features) f: sin/cos(h theta_m) for the mechanical harmonics h of the rotor angle (the electrical
harmonics are h / p), the motor speed, the driven-pair current and the surface angle, each scaled to
O(1). Output: T = s (w_0 + w_lin . f + w_hid . tanh(W f + b)) [N m] (or [V]), s = ``output_scale``.
The hidden layer (W, b) is random and fixed (seeded); the output weights w are fitted through the
simulator by batched Gauss-Newton with a ridge prior, the calibrated model frozen (a random-feature
network: its output is linear in w, so the fit converges in a few iterations, each one batched simulator
call of n_weights + 1 rows). The closure is an
:class:`~phm_torch.effects.Effect` whose hook is the network, so the simulator is unchanged.

Attribution: mean |dT/df_j| * std(f_j) over the fitted trajectory (input-gradient x input spread, by
autograd through the network), summed per input group (one group per harmonic: its sin and cos) and
normalised to shares. The dominant groups are the lead for writing the missing effect.
"""

from __future__ import annotations

import inspect
import logging
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace

import numpy as np
import torch

from .. import checks
from ..effects import EFFECTS
from ..effects.base import ACTUATOR_UNITS
from ..params import ActuatorParams
from ..simulator import EMASimulator
from .calibrate import Calibration, FitSettings, fit_models
from .closure_net import EQUATIONS, ClosureNet, NeuralClosure
from .model import threads
from .parameters import FreeParameter, ParameterSpace

log = logging.getLogger(__name__)
_NET = inspect.signature(ClosureNet).parameters  # equation, output_scale, seed: the network's own defaults


@dataclass
class Attribution:
    """Shares of the closure output's sensitivity per input group (sum 1), largest first, and its RMS."""

    shares: dict[str, float]
    output_rms: float
    unit: str


def attribute(net: ClosureNet, weights: torch.Tensor, feats: torch.Tensor) -> Attribution:
    """Input-gradient attribution of the fitted closure over trajectory features (T, d)."""
    with torch.enable_grad():
        f = feats.detach().clone().requires_grad_(True)
        y = net(f, weights.detach().to(f.dtype))
        (grad,) = torch.autograd.grad(y.sum(), f)
    score = grad.abs().mean(0) * f.detach().std(0)
    total = {g: float(score[idx].sum()) for g, idx in net.groups().items()}
    s = sum(total.values())
    shares = {g: v / s if s > 0 else 0.0 for g, v in sorted(total.items(), key=lambda t: -t[1])}
    rms = float(net.output_scale * y.detach().pow(2).mean().sqrt())
    return Attribution(shares, rms, "N m" if net.equation == "torque" else "V")


def scales_from(simulated: Sequence[dict[str, torch.Tensor]]) -> tuple[float, float, float]:
    """Input normalisers (max |speed|, max |current|, max |surface angle|) from simulated records."""

    def top(c: str) -> float:
        return max(float(np.max(np.abs(s[c].numpy()))) for s in simulated) or 1.0

    return top("speed"), top("current"), top("user_angle")


# The unit of the closure's output weights on an actuator, when ``closure.output_scale`` is not given: a
# 1200th of its peak motor torque 2 k_e I_max (torque equation) or a 28,000th of its bus voltage (voltage),
# 1e-3 N m and 1e-3 V on the default datasheet. The ridge prior and the weights' bound are in this unit, so a
# fixed one would shrink a larger actuator's closure (its missing torque needs larger weights).
OUTPUT_UNIT = {"torque": ("peak_motor_torque", 1 / 1200), "voltage": ("supply_voltage", 1 / 28000)}


def output_scale(cs: ClosureSettings, params: ActuatorParams) -> float:
    """The closure's output unit [N m] or [V]: ``cs.output_scale``, or sized by the actuator ``params``."""
    if cs.output_scale is not None:
        return float(cs.output_scale)
    unit, fraction = OUTPUT_UNIT[cs.equation]
    return fraction * ACTUATOR_UNITS[unit](params)


@dataclass(frozen=True)
class ClosureSettings:
    """Neural closure: ``enabled`` ``auto`` (when no candidate is significant, the residual is not white and the
    NRMSE exceeds ``ratio`` x the noise floor), ``always`` or ``never``; the network (see :class:`ClosureNet`),
    its ridge prior weight, finite-difference step and fit settings.

    ``harmonics``: rotor-angle orders fed to the network; ``None`` (default) derives them from the actuator
    (:func:`~.orders.closure_orders`: 1, 2, p, 2p, the cogging order and its double, 6p, the pinion's teeth)
    plus the residual's ``data_orders`` strongest orders. ``equation``: ``torque`` (motor shaft) or
    ``voltage`` (driven pair). ``hidden``: random tanh units (the output weights are fitted through the
    simulator); ``output_scale``: [N m] (torque) or [V] (voltage) per unit weight, ``None`` (default): sized
    by the actuator (:data:`OUTPUT_UNIT`); ``ridge``: prior weight on the output weights; ``fit``: its Gauss-Newton iterations (the calibrated model frozen; one simulator call
    each)."""

    enabled: str = "auto"
    equation: str = _NET["equation"].default
    harmonics: tuple[int, ...] | None = None
    data_orders: int = 3
    hidden: int = 8
    output_scale: float | None = None
    ridge: float = 1.0
    fd_step: float = 0.05
    ratio: float = 1.5
    seed: int = _NET["seed"].default
    fit: FitSettings = field(default_factory=lambda: FitSettings(max_iter=4, lambdas=(1.0,)))

    def __post_init__(self) -> None:
        if self.enabled not in ("auto", "always", "never"):
            raise ValueError(f"closure.enabled must be auto, always or never, got {self.enabled!r}")
        if self.equation not in EQUATIONS:
            raise ValueError(f"closure.equation must be one of {list(EQUATIONS)}, got {self.equation!r}")
        if not isinstance(self.fit, FitSettings):
            raise ValueError(f"closure.fit must be FitSettings, got {self.fit!r}")
        values = {
            "data_orders": checks.integer(self.data_orders, "closure.data_orders", 0),
            "hidden": checks.integer(self.hidden, "closure.hidden", 0),
            "ridge": checks.number(self.ridge, "closure.ridge", 0.0),
            "fd_step": checks.number(self.fd_step, "closure.fd_step", 0.0, True),
            "ratio": checks.number(self.ratio, "closure.ratio", 0.0, True),
            "seed": checks.integer(self.seed, "closure.seed", 0),
        }
        if self.output_scale is not None:  # None: sized by the actuator
            values["output_scale"] = checks.number(self.output_scale, "closure.output_scale", 0.0, True)
        if self.harmonics is not None:  # None: from the actuator's orders and the residual's
            if isinstance(self.harmonics, (str, bytes)) or not hasattr(self.harmonics, "__iter__"):
                raise ValueError(f"closure.harmonics must be null or a list of orders, got {self.harmonics!r}")
            values["harmonics"] = tuple(
                checks.integer(h, f"closure.harmonics[{i}]", 1) for i, h in enumerate(self.harmonics)
            )
        for key, value in values.items():
            object.__setattr__(self, key, value)


@dataclass
class ClosureResult:
    """The model with the fitted closure, and what the closure depends on."""

    calibration: Calibration
    attribution: Attribution
    harmonics: tuple[int, ...] = ()


def fit_closure(
    cal: Calibration,
    cs: ClosureSettings,
    noise: Callable[[np.ndarray, float], float],
    fidelity: str,
    device: str | torch.device = "cpu",
    harmonics: Sequence[int] | None = None,
) -> ClosureResult:
    """Fit a closure on top of ``cal``'s calibrated model and attribute it.

    The calibrated parameters are frozen at their values (they become part of the fixed model) and only the
    closure's output weights are fitted: the network's output is linear in them, so Gauss-Newton with a
    ridge prior converges in a few iterations of (n_weights + 1) simulated rows each. ``harmonics`` (the
    rotor-angle orders of the inputs) overrides ``cs.harmonics``; one of them must be given.
    """
    harmonics = cs.harmonics if harmonics is None else harmonics
    if harmonics is None:
        raise ValueError("closure.harmonics: no orders given (the workbench derives them from the actuator)")
    scale = output_scale(cs, cal.space.params)
    net = ClosureNet(
        harmonics, cs.hidden, *scales_from(cal.simulated), equation=cs.equation, output_scale=scale, seed=cs.seed
    )
    unit = "N m" if cs.equation == "torque" else "V"
    weights = tuple(
        FreeParameter(f"closure.w{i}", "closure", (i,), 0.0, -1e3, 1e3, cs.fd_step, unit, factor=scale)
        for i in range(net.n_weights)
    )
    base = freeze(cal)
    sp = replace(base, closure=net, free=weights, label=f"{cal.label} + closure")
    prior = torch.full((net.n_weights,), math.sqrt(cs.ridge), dtype=torch.float64)

    def progress(it: int, costs: list[float]) -> None:
        log.info("closure: iteration %d, chi2/2 + prior %.1f", it, costs[0])

    fitted = fit_models(cal.evaluator, [sp], [None], cal.sigma, noise, cs.fit, priors=[prior], on_iteration=progress)[0]
    feats = trace_features(fitted, net, fidelity, device)
    return ClosureResult(fitted, attribute(net, fitted.x, feats), tuple(net.harmonics))


def freeze(cal: Calibration) -> ParameterSpace:
    """``cal``'s model with its free parameters fixed at the fitted values (no free parameter left)."""
    k, scales, eff, _ = cal.space.settings(cal.x.reshape(1, -1))
    params = cal.space.params.replace(
        **{f: float(getattr(cal.space.params, f)) * float(v[0]) for f, v in scales.items()}
    )
    effects = {n: {key: float(v[0]) for key, v in vals.items()} for n, vals in eff.items()}
    return replace(cal.space, params=params, faults=tuple(float(v) for v in k[0]), effects=effects, free=())


def trace_features(
    cal: Calibration, net: ClosureNet, fidelity: str, device: str | torch.device = "cpu"
) -> torch.Tensor:
    """Closure input features along the fitted trajectory of the first record, (T, d) (one short B = 1 run)."""
    rec = cal.evaluator.records[0]
    k, scales, eff, w = cal.space.settings(cal.x.reshape(1, -1))
    trace: list[torch.Tensor] = []
    effects = [EFFECTS[n](**v) for n, v in eff.items()] + [NeuralClosure(net, w, trace)]
    sim = EMASimulator(cal.space.params, fidelity, effects=effects, device=device)
    with torch.no_grad(), threads(cal.evaluator.threads):
        sim.run(k, rec.command, rec.duration, scales=scales, channels=["position"])
    return torch.stack(trace)
