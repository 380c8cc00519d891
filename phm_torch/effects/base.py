"""Physical-effect interface and registry.

An effect is a small named module with physical parameters, off unless enabled, that acts on the
shared plant, mechanics or drive through the hooks below, so the same effect works in every fidelity.
Every effect is parameterised so that its ``strength`` parameters at zero leave the model unchanged:
that is what lets the workbench run a score test at zero for effects not in the model.
"""

from __future__ import annotations

import copy
import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, ClassVar

import torch

if TYPE_CHECKING:
    from ..plant import Plant


@dataclass(frozen=True)
class EffectParam:
    """Declaration of one effect parameter.

    Attributes:
        default: value used by ``+effects.NAME={}`` [unit].
        unit: physical unit, for reports.
        description: one line.
        minimum: smallest admissible value (``None`` = any finite value).
        scale: typical magnitude, used to normalise fits and score tests [unit], or, with ``per``, a multiple
            of that actuator quantity (``ACTUATOR_UNITS``); read it through :meth:`scale_for`.
        per: name of the actuator quantity ``scale`` is a multiple of; ``""``: ``scale`` is absolute.
    """

    default: float
    unit: str
    description: str
    minimum: float | None = 0.0
    scale: float = 1.0
    per: str = ""

    def __post_init__(self) -> None:
        if self.per and self.per not in ACTUATOR_UNITS:
            raise ValueError(f"EffectParam.per: unknown actuator unit {self.per!r}; known: {sorted(ACTUATOR_UNITS)}")

    def scale_for(self, params: Any) -> float:
        """The typical magnitude on the actuator ``params`` [unit]: ``scale`` itself, or ``scale`` times the
        actuator quantity ``per`` (so a fit's normalisation and bound and a score test's probe follow the
        actuator's size, not the reference's)."""
        if not self.per:
            return self.scale
        unit = ACTUATOR_UNITS[self.per](params)
        if not (math.isfinite(unit) and unit > 0):
            raise ValueError(f"actuator unit {self.per!r} must be positive and finite, got {unit!r}")
        return self.scale * unit


def _peak_motor_torque(params: Any) -> float:
    # torque of the conducting pair at the current limit, 2 k_e I_max [N m]: every datasheet has it (all > 0)
    return 2.0 * float(params.back_emf_constant) * float(params.current_limit)


# Actuator quantities an effect parameter's typical magnitude may be a multiple of (``EffectParam.per``).
ACTUATOR_UNITS: dict[str, Callable[[Any], float]] = {
    "peak_motor_torque": _peak_motor_torque,  # [N m], motor side
    "peak_user_torque": lambda p: _peak_motor_torque(p) * float(p.gear_ratio),  # [N m], user side
    "motor_damping": lambda p: _peak_motor_torque(p) / float(p.speed_limit),  # [N m s/rad], motor side
    "speed_limit": lambda p: float(p.speed_limit),  # [rad/s], motor side
    "current_limit": lambda p: float(p.current_limit),  # [A]
    "pwm_period": lambda p: 1.0 / float(p.pwm_frequency),  # [s]
    "supply_voltage": lambda p: float(p.supply_voltage),  # [V]
    "output_stiffness": lambda p: float(p.output_stiffness),  # [N m/rad], user side
    "output_compliance": lambda p: 1.0 / float(p.output_stiffness),  # [rad/(N m)], user side
}


@dataclass
class EffectContext:
    """State seen by the per-substep hooks; every tensor is (B,).

    Attributes:
        time: 0-d tensor [s].  theta_m, omega_m: motor angle [rad], speed [rad/s].
        theta_u, omega_u: user angle [rad], speed [rad/s].  current: driven-pair (HF) or DC (LF) current [A].
        plant: the per-sample parameters.
    """

    time: torch.Tensor
    theta_m: torch.Tensor
    omega_m: torch.Tensor
    theta_u: torch.Tensor
    omega_u: torch.Tensor
    current: torch.Tensor
    plant: Any


class Effect:
    """Base class: override the hooks the effect needs; the rest add nothing.

    Subclasses declare ``name``, ``PARAMS`` and ``STRENGTH`` (the parameters whose zero turns the effect
    off). Parameter values are tensors (scalar or (B,)) in ``self.values`` and may require grad.
    """

    name: ClassVar[str] = ""
    PARAMS: ClassVar[dict[str, EffectParam]] = {}
    STRENGTH: ClassVar[tuple[str, ...]] = ()
    explains: ClassVar[str] = ""  # the residual signature this effect produces, for reports

    def __init__(self, **values: Any):
        unknown = sorted(set(values) - set(self.PARAMS))
        if unknown:
            raise ValueError(f"effects.{self.name}: unknown parameter(s) {unknown}; known: {sorted(self.PARAMS)}")
        self.values: dict[str, torch.Tensor] = {}
        for key, spec in self.PARAMS.items():
            v = values.get(key, spec.default)
            t = torch.as_tensor(v, dtype=torch.float64) if not torch.is_tensor(v) else v
            if not torch.isfinite(t).all():
                raise ValueError(f"effects.{self.name}.{key} must be finite, got {v!r}")
            if spec.minimum is not None and (t < spec.minimum).any():
                raise ValueError(f"effects.{self.name}.{key} must be >= {spec.minimum} {spec.unit}, got {v!r}")
            self.values[key] = t

    def __getitem__(self, key: str) -> torch.Tensor:
        return self.values[key]

    def __repr__(self) -> str:
        vals = ", ".join(f"{k}={v.detach().cpu().tolist()}" for k, v in self.values.items())
        return f"{type(self).__name__}({vals})"

    def to(self, dtype: torch.dtype, device: str | torch.device) -> Effect:
        """A copy whose values are on ``dtype``/``device`` (``.to`` keeps their grads); ``self`` is unchanged."""
        out = copy.copy(self)
        out.values = {k: v.to(dtype=dtype, device=device) for k, v in self.values.items()}
        return out

    # ---- hooks ---------------------------------------------------------------------------------
    def modify_plant(self, plant: Plant) -> Plant:
        """The plant with static per-sample parameters changed (run once, after the faults).

        Return a new plant (``dataclasses.replace(plant, field=...)``); the plant is frozen.
        """
        return plant

    def motor_torque(self, ctx: EffectContext) -> torch.Tensor | float:
        """Extra torque on the motor shaft [N m], positive in the direction of positive motion."""
        return 0.0

    def friction_torque(self, ctx: EffectContext) -> torch.Tensor | float:
        """Extra kinetic friction magnitude [N m] while sliding (applied against the motion)."""
        return 0.0

    def breakaway_torque(self, ctx: EffectContext) -> torch.Tensor | float:
        """Extra static friction [N m] that must be overcome to leave sticking."""
        return 0.0

    def load_torque(self, ctx: EffectContext) -> torch.Tensor | float:
        """External torque on the user side [N m], positive opposing positive motion."""
        return 0.0

    def emf_scale(self, ctx: EffectContext) -> torch.Tensor | float:
        """Factor on the back-EMF/torque constant [-]."""
        return 1.0

    def voltage_error(self, ctx: EffectContext) -> torch.Tensor | float:
        """Error added to the commanded line voltage of the driven pair [V]."""
        return 0.0


EFFECTS: dict[str, type[Effect]] = {}


def register_effect(cls: type[Effect]) -> type[Effect]:
    """Class decorator adding an effect to the registry under ``cls.name``."""
    if not cls.name or not cls.name.isidentifier():
        raise ValueError(f"effect class {cls.__name__} needs an identifier 'name', got {cls.name!r}")
    if cls.name in EFFECTS and EFFECTS[cls.name] is not cls:
        raise ValueError(f"effect {cls.name!r} is already registered by {EFFECTS[cls.name].__name__}")
    for s in cls.STRENGTH:
        if s not in cls.PARAMS:
            raise ValueError(f"effect {cls.name!r}: strength parameter {s!r} is not declared in PARAMS")
    EFFECTS[cls.name] = cls
    return cls


def sized_defaults(name: str, params: Any | None) -> dict[str, float]:
    """Defaults of effect ``name``'s shape parameters sized by the actuator (``EffectParam.per``, e.g. a
    Stribeck velocity or a saturation current) on ``params``: their typical magnitude there, so an effect added
    without them takes the actuator's size, not the reference's (where each equals its declared default).
    Strengths keep their declared defaults; ``params`` None: no sized defaults (the declared ones apply)."""
    if params is None:
        return {}
    cls = EFFECTS[name]
    return {k: spec.scale_for(params) for k, spec in cls.PARAMS.items() if spec.per and k not in cls.STRENGTH}


def build_effects(spec: Mapping[str, Mapping[str, Any] | None] | None, params: Any | None = None) -> list[Effect]:
    """Instantiate effects from a ``{name: {param: value}}`` mapping (``None``/``{}`` = defaults; with the
    actuator ``params``, shape parameters sized by it default to their typical magnitude there,
    :func:`sized_defaults`)."""
    effects = []
    for name, values in (spec or {}).items():
        if name not in EFFECTS:
            raise ValueError(f"effects: unknown effect {name!r}; available: {sorted(EFFECTS)}")
        values = {**sized_defaults(name, params), **dict(values or {})}
        for key, v in values.items():
            if isinstance(v, bool) or (not torch.is_tensor(v) and not isinstance(v, (int, float))):
                raise ValueError(f"effects.{name}.{key} must be a number, got {v!r}")
            if not torch.is_tensor(v) and not math.isfinite(v):
                raise ValueError(f"effects.{name}.{key} must be finite, got {v!r}")
        effects.append(EFFECTS[name](**values))
    return effects
