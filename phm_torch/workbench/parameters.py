"""Free parameters of a model and their map to simulator inputs.

A :class:`ParameterSpace` is a model (datasheet + base fault vector + effects with their values) plus the
list of parameters a fit may move. The fit works on a normalised vector x:

* ``scale``: x = log(multiplier) of one datasheet field or of a named group of fields (e.g. ``dry_friction``
  = Coulomb and static friction together); value reported = nominal * multiplier (a group: the multiplier);
* ``fault``: x = k_i, the fault-vector entry, in [0, 1];
* ``effect``: x = value / scale of an effect parameter (``EffectParam.scale_for`` the actuator);
* ``closure``: x = one output weight of the neural closure.

``settings(X)`` turns a batch (P, n) of such vectors into the simulator's faults (P, 8), scales and effect
values, each (P,), so that P candidate models run in one batched call.
"""

from __future__ import annotations

import math
import re
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, replace
from typing import Any

import torch

from ..effects import EFFECTS, sized_defaults
from ..faults import FAULT_NAMES, N_FAULTS
from ..params import ActuatorParams
from ..plant import TENSOR_FIELDS

_FAULT_KEY = re.compile(r"^k([1-8])$")
EFFECT_BOUND = 100.0  # |x| bound of effect parameters without a declared minimum, in units of their scale


@dataclass(frozen=True)
class FreeParameter:
    """One fitted parameter.

    Attributes:
        name: reported name (``back_emf_constant``, ``dry_friction``, ``k8``, ``cogging_torque.amplitude``...).
        kind: ``scale``, ``fault``, ``effect`` or ``closure``.
        targets: datasheet fields (scale), ``(index,)`` (fault), ``(effect, param)`` (effect), ``(index,)`` (closure).
        x0, lower, upper: start and bounds of the normalised value x.
        step: forward-difference step of x.
        unit: unit of the reported value.  nominal: nominal physical value (scale of one field) or 1.
        factor: reported value = factor * x for ``effect`` and ``closure``.
    """

    name: str
    kind: str
    targets: tuple[Any, ...]
    x0: float
    lower: float
    upper: float
    step: float
    unit: str = ""
    nominal: float = 1.0
    factor: float = 1.0

    def value(self, x: float) -> float:
        """Reported physical value of the normalised x."""
        if self.kind == "scale":
            return self.nominal * math.exp(x)
        return self.factor * x

    def std(self, x: float, std_x: float) -> float:
        """Standard deviation of the reported value (delta method) from that of x."""
        if self.kind == "scale":
            return self.nominal * math.exp(x) * std_x
        return abs(self.factor) * std_x


@dataclass(frozen=True)
class ParameterSpace:
    """A model and its free parameters.

    Attributes:
        params: the datasheet.  faults: base fault vector (8,).
        effects: the model's effects, {name: {param: value}} with every parameter filled in.
        free: the fitted parameters, in the order of x.
        closure: optional neural closure (``phm_torch.workbench.closure.ClosureNet``), its weights free.
        label: name in reports.
    """

    params: ActuatorParams
    faults: tuple[float, ...]
    effects: Mapping[str, Mapping[str, float]] = field(default_factory=dict)
    free: tuple[FreeParameter, ...] = ()
    closure: Any = None
    label: str = "model"

    @property
    def n(self) -> int:
        return len(self.free)

    def vector(self, attr: str) -> torch.Tensor:
        """``x0``, ``lower``, ``upper`` or ``step`` of every free parameter, (n,)."""
        return torch.tensor([getattr(p, attr) for p in self.free], dtype=torch.float64)

    def names(self) -> list[str]:
        return [p.name for p in self.free]

    def settings(
        self, x: torch.Tensor
    ) -> tuple[torch.Tensor, dict[str, torch.Tensor], dict[str, dict[str, torch.Tensor]], torch.Tensor | None]:
        """Simulator inputs of a batch of parameter vectors.

        Args:
            x: (P, n) normalised parameters.
        Returns:
            faults (P, 8); scales {field: (P,)}; effect values {effect: {param: (P,)}} for this model's
            effects; closure weights (P, n_weights) or ``None``.
        """
        if x.ndim != 2 or x.shape[1] != self.n:
            raise ValueError(f"parameter batch must be (P, {self.n}), got {tuple(x.shape)}")
        p = x.shape[0]
        x = x.to(torch.float64)
        faults = torch.tensor(self.faults, dtype=torch.float64).expand(p, N_FAULTS).clone()
        scales: dict[str, torch.Tensor] = {}
        effects = {
            name: {k: torch.full((p,), float(v), dtype=torch.float64) for k, v in vals.items()}
            for name, vals in self.effects.items()
        }
        weights = None
        if self.closure is not None:
            weights = torch.zeros(p, self.closure.n_weights, dtype=torch.float64)
        for j, fp in enumerate(self.free):
            col = x[:, j]
            if fp.kind == "scale":
                for target in fp.targets:
                    scales[target] = scales.get(target, 1.0) * torch.exp(col)
            elif fp.kind == "fault":
                faults[:, fp.targets[0]] = col
            elif fp.kind == "effect":
                effects[fp.targets[0]][fp.targets[1]] = fp.factor * col
            elif fp.kind == "closure":
                weights[:, fp.targets[0]] = col
        return faults, scales, effects, weights

    def effect_values(self, x: torch.Tensor) -> dict[str, dict[str, float]]:
        """The model's effects with the fitted values of x (n,) filled in."""
        _, _, eff, _ = self.settings(x.reshape(1, -1))
        return {name: {k: float(v[0]) for k, v in vals.items()} for name, vals in eff.items()}

    def with_effect(
        self,
        name: str,
        values: Mapping[str, float],
        free: Sequence[str],
        x: torch.Tensor,
        fd_step: float,
        label: str | None = None,
    ) -> tuple[ParameterSpace, torch.Tensor]:
        """This model plus effect ``name`` (its parameters ``free`` fitted, the others fixed at ``values``).

        Args:
            values: full or partial parameter values of the effect (defaults fill the rest).
            free: parameters of the effect to fit.
            x: (n,) current values of this space's parameters (kept as the start).
        Returns:
            The new space and its start vector (n + len(free),).
        """
        if name in self.effects:
            raise ValueError(f"effect {name!r} is already in the model")
        full = effect_defaults(name, values, self.params)
        new_free = [effect_parameter(name, key, full[key], fd_step, self.params) for key in free]
        space = replace(
            self,
            effects={**self.effects, name: full},
            free=(*self.free, *new_free),
            label=label or f"{self.label} + {name}",
        )
        x_new = torch.cat([x.to(torch.float64), torch.tensor([p.x0 for p in new_free], dtype=torch.float64)])
        return space, x_new

    def fitted(self, x: torch.Tensor, std_x: torch.Tensor | None = None) -> dict[str, tuple[float, float]]:
        """{name: (value, std)} of the free parameters (std NaN when not given)."""
        out = {}
        for j, fp in enumerate(self.free):
            xv = float(x[j])
            s = float(std_x[j]) if std_x is not None else math.nan
            out[fp.name] = (fp.value(xv), fp.std(xv, s) if math.isfinite(s) else math.nan)
        return out


def effect_defaults(
    name: str, values: Mapping[str, Any] | None = None, params: ActuatorParams | None = None
) -> dict[str, float]:
    """Every parameter of effect ``name``: the given values, the defaults for the rest (with the actuator
    ``params``, shape parameters sized by it at their typical magnitude there: :func:`~phm_torch.effects.sized_defaults`)."""
    if name not in EFFECTS:
        raise ValueError(f"effects: unknown effect {name!r}; available: {sorted(EFFECTS)}")
    cls = EFFECTS[name]
    values = dict(values or {})
    unknown = sorted(set(values) - set(cls.PARAMS))
    if unknown:
        raise ValueError(f"effects.{name}: unknown parameter(s) {unknown}; known: {sorted(cls.PARAMS)}")
    values = {**sized_defaults(name, params), **values}
    out = {}
    for key, spec in cls.PARAMS.items():
        v = values.get(key, spec.default)
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
            raise ValueError(f"effects.{name}.{key} must be a finite number, got {v!r}")
        if spec.minimum is not None and v < spec.minimum:
            raise ValueError(f"effects.{name}.{key} must be >= {spec.minimum} {spec.unit}, got {v!r}")
        out[key] = float(v)
    return out


def effect_parameter(name: str, key: str, value: float, fd_step: float, params: ActuatorParams) -> FreeParameter:
    """A free effect parameter, normalised by its typical magnitude on the actuator ``params``
    (``EffectParam.scale_for``); bounds from its declared minimum."""
    cls = EFFECTS[name]
    if key not in cls.PARAMS:
        raise ValueError(f"effects.{name}: unknown parameter {key!r}; known: {sorted(cls.PARAMS)}")
    spec = cls.PARAMS[key]
    scale = spec.scale_for(params)
    lower = -EFFECT_BOUND if spec.minimum is None else spec.minimum / scale
    x0 = min(max(value / scale, lower), EFFECT_BOUND)
    return FreeParameter(
        f"{name}.{key}", "effect", (name, key), x0, lower, EFFECT_BOUND, fd_step, spec.unit, factor=scale
    )


def build_space(
    params: ActuatorParams,
    free: Sequence[str],
    groups: Mapping[str, Sequence[str]] | None = None,
    faults: Sequence[float] | None = None,
    effects: Mapping[str, Mapping[str, Any] | None] | None = None,
    effect_free: Mapping[str, Sequence[str]] | None = None,
    scale_bounds: tuple[float, float] = (0.2, 5.0),
    fd_step: float = 1e-2,
    label: str = "model",
) -> ParameterSpace:
    """The model to calibrate.

    Args:
        params: the datasheet.
        free: names of the free parameters: datasheet fields (multiplicative scale), group names, ``k1``..``k8``
            (fault-vector entries) or ``EFFECT.PARAM`` (a parameter of one of the model's effects).
        groups: {group name: [datasheet fields]} sharing one multiplier.
        faults: base fault vector (default the actuator's nominal one).
        effects: the model's effects {name: {param: value}} (missing values: defaults).
        effect_free: {effect: [params]} fitted for the model's effects, besides those named in ``free``
            (default: every effect's strength parameters).
        scale_bounds: (min, max) multiplier of scale parameters.
        fd_step: forward-difference step of the normalised parameters.
    """
    groups = dict(groups or {})
    lo, hi = scale_bounds
    if not (0 < lo < 1 < hi and math.isfinite(hi)):
        raise ValueError(f"scale_bounds must satisfy 0 < min < 1 < max, got {list(scale_bounds)}")
    if not (math.isfinite(fd_step) and fd_step > 0):
        raise ValueError(f"calibration.fd_step must be > 0, got {fd_step!r}")
    for gname, fields_ in groups.items():
        if gname in TENSOR_FIELDS:
            raise ValueError(f"groups.{gname}: a group may not be named like a datasheet field")
        bad = [f for f in fields_ or [] if f not in TENSOR_FIELDS]
        if bad or not fields_:
            raise ValueError(
                f"groups.{gname}: unknown or missing datasheet field(s) {bad or fields_}; known: {list(TENSOR_FIELDS)}"
            )
    base_faults = tuple(float(v) for v in (faults if faults is not None else params.nominal_faults))
    model_effects = {name: effect_defaults(name, vals, params) for name, vals in (effects or {}).items()}
    out: list[FreeParameter] = []
    for name in free:
        if not isinstance(name, str):
            raise ValueError(f"free: entries must be parameter names, got {name!r}")
        m = _FAULT_KEY.match(name)
        if m:
            i = int(m.group(1)) - 1
            out.append(
                FreeParameter(f"k{i + 1}", "fault", (i,), base_faults[i], 0.0, 1.0, fd_step, f"- ({FAULT_NAMES[i]})")
            )
        elif name in groups:
            out.append(
                FreeParameter(name, "scale", tuple(groups[name]), 0.0, math.log(lo), math.log(hi), fd_step, "x nominal")
            )
        elif name in TENSOR_FIELDS:
            out.append(
                FreeParameter(
                    name, "scale", (name,), 0.0, math.log(lo), math.log(hi), fd_step, "", float(getattr(params, name))
                )
            )
        elif "." in name and name.split(".", 1)[0] in model_effects:
            eff, key = name.split(".", 1)
            out.append(effect_parameter(eff, key, model_effects[eff].get(key, math.nan), fd_step, params))
        else:
            raise ValueError(
                f"free: unknown parameter {name!r}; use a datasheet field {list(TENSOR_FIELDS)}, "
                f"a group {sorted(groups)}, k1..k8, or EFFECT.PARAM of a model effect"
            )
    for eff in model_effects:
        keys = (effect_free or {}).get(eff, EFFECTS[eff].STRENGTH)
        for key in keys:
            if f"{eff}.{key}" not in [p.name for p in out]:
                out.append(effect_parameter(eff, key, model_effects[eff][key], fd_step, params))
    names = [p.name for p in out]
    dup = sorted({n for n in names if names.count(n) > 1})
    if dup:
        raise ValueError(f"free: parameter(s) {dup} listed twice")
    return ParameterSpace(params, base_faults, model_effects, tuple(out), None, label)
