"""Actuator parameters: one validated record of the datasheet values.

The values themselves live in ``conf/actuator/*.yaml`` (one home); this module only defines the
fields, their units and their validation.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping
from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import Any

from omegaconf import OmegaConf

CONF_DIR = Path(__file__).resolve().parent.parent / "conf"

# Fields that may be zero (all others must be strictly positive).
_NON_NEGATIVE = {
    "motor_viscous",
    "coulomb_friction",
    "static_friction",
    "backlash",
    "user_damping",
    "output_damping",
    "end_stop_damping",
    "speed_integral_gain",
    "current_integral_gain",
    "lvdt_time_constant",
}
_INTEGER = {"pole_pairs", "stator_slots"}


@dataclass(frozen=True)
class LFShape:
    """Fitted shape-function coefficients of the low-fidelity motor (see ``physics/dc_motor.py``).

    Attributes:
        emf_short_gain: a_k, the pair EMF constant falls as k_e * (1 - a_k * s) per shorted phase.
        resistance_short_gain: a_R, the pair resistance falls as R * (1 - a_R * s).
        inductance_short_exponent: a_L, the pair inductance falls as L * (1 - s) ** a_L.
        commutation_width: electrical angle [rad] over which the shape functions blend between sectors.
    """

    emf_short_gain: float = 1.0
    resistance_short_gain: float = 1.0
    inductance_short_exponent: float = 2.0
    commutation_width: float = 0.0


@dataclass(frozen=True)
class ActuatorParams:
    """Nominal parameters of one electromechanical actuator, SI units (see conf/actuator/*.yaml)."""

    supply_voltage: float
    pwm_frequency: float
    pole_pairs: int
    stator_slots: int
    phase_resistance: float
    phase_inductance: float
    back_emf_constant: float
    motor_inertia: float
    motor_viscous: float
    coulomb_friction: float
    static_friction: float
    gear_ratio: float
    output_stiffness: float
    output_damping: float
    backlash: float
    user_inertia: float
    user_damping: float
    end_stop_angle: float
    end_stop_stiffness: float
    end_stop_damping: float
    position_gain: float
    speed_limit: float
    speed_gain: float
    speed_integral_gain: float
    current_limit: float
    current_gain: float
    current_integral_gain: float
    lvdt_time_constant: float
    filter_cutoff: float
    sample_rate: float
    short_circuit_max: float
    nominal_faults: tuple[float, ...]
    lf_shape: LFShape = field(default_factory=LFShape)
    # Optional, 0 = not declared: teeth of the pinion on the motor shaft, the gear-mesh order per motor turn
    # (the workbench adds it to the rotor-angle orders it analyses).
    pinion_teeth: int = 0

    def __post_init__(self) -> None:
        for f in fields(self):
            name, value = f.name, getattr(self, f.name)
            if name in ("nominal_faults", "lf_shape"):
                continue
            if name == "pinion_teeth":
                if isinstance(value, bool) or int(value) != value or value < 0:
                    raise ValueError(f"actuator.{name} must be an integer >= 0 (0 = not declared), got {value!r}")
                continue
            if name in _INTEGER:
                if int(value) != value or value <= 0:
                    raise ValueError(f"actuator.{name} must be a positive integer, got {value!r}")
                continue
            if not isinstance(value, (int, float)) or not math.isfinite(value):
                raise ValueError(f"actuator.{name} must be a finite number, got {value!r}")
            if name in _NON_NEGATIVE:
                if value < 0:
                    raise ValueError(f"actuator.{name} must be >= 0, got {value!r}")
            elif value <= 0:
                raise ValueError(f"actuator.{name} must be > 0, got {value!r}")
        if len(self.nominal_faults) != 8:
            raise ValueError(f"actuator.nominal_faults must have 8 entries, got {len(self.nominal_faults)}")
        if not 0 < self.short_circuit_max < 1:
            raise ValueError(f"actuator.short_circuit_max must be in (0, 1), got {self.short_circuit_max}")
        if self.static_friction < self.coulomb_friction:
            raise ValueError(
                f"actuator.static_friction ({self.static_friction}) must be >= "
                f"coulomb_friction ({self.coulomb_friction})"
            )
        # the acquisition grid falls on control periods (a divisor) or on substeps of each (a multiple)
        if self.sample_rate % 1 or self.pwm_frequency % self.sample_rate and self.sample_rate % self.pwm_frequency:
            raise ValueError(
                f"actuator.sample_rate ({self.sample_rate}) must be a multiple or divisor "
                f"of pwm_frequency ({self.pwm_frequency})"
            )

    @property
    def nyquist_attenuation_db(self) -> float:
        """Gain [dB] of the envelope current's 2nd-order Butterworth filter at half the sample rate: how much of
        what lies above the Nyquist frequency the filter removes before sampling (-40 dB on the reference; above
        about -20 dB the sampled current aliases the PWM and commutation ripple)."""
        ratio = self.sample_rate / 2 / self.filter_cutoff
        return -10 * math.log10(1 + ratio**4)

    @property
    def control_period(self) -> float:
        """Period of the discrete controller and of the PWM carrier [s]."""
        return 1.0 / self.pwm_frequency

    def replace(self, **changes: Any) -> ActuatorParams:
        """Return a copy with some fields changed (validated again)."""
        return dataclasses.replace(self, **changes)

    @classmethod
    def from_mapping(cls, data: Mapping[str, Any]) -> ActuatorParams:
        """Build from a plain mapping (e.g. a Hydra ``actuator`` node); unknown keys are errors."""
        data = dict(data)
        data.pop("_target_", None)
        known = {f.name for f in fields(cls)}
        unknown = sorted(set(data) - known)
        if unknown:
            raise ValueError(f"actuator: unknown parameter(s) {unknown}; known: {sorted(known)}")
        missing = sorted(
            f.name
            for f in fields(cls)
            if f.name not in data and f.default is dataclasses.MISSING and f.default_factory is dataclasses.MISSING
        )
        if missing:
            raise ValueError(f"actuator: missing parameter(s) {missing}")
        shape = data.pop("lf_shape", None) or {}
        shape_known = {f.name for f in fields(LFShape)}
        bad = sorted(set(shape) - shape_known)
        if bad:
            raise ValueError(f"actuator.lf_shape: unknown coefficient(s) {bad}; known: {sorted(shape_known)}")
        data["nominal_faults"] = tuple(float(v) for v in data["nominal_faults"])
        return cls(**data, lf_shape=LFShape(**{k: float(v) for k, v in shape.items()}))


def config_file(group: str, name: str) -> Path:
    """``conf/<group>/<name>.yaml`` for a bare name, else ``name`` as a path to a YAML file.

    Raises:
        ValueError: no such file (the message starts with ``group``).
    """
    path = Path(name)
    if not path.suffix:
        path = CONF_DIR / group / f"{name}.yaml"
    if not path.is_file():
        raise ValueError(f"{group}: no such {group} file {str(path)!r}")
    return path


def load_actuator(name: str = "ema_reference", **overrides: Any) -> ActuatorParams:
    """Load ``conf/actuator/<name>.yaml`` (or a path to a YAML file) with optional overrides."""
    path = config_file("actuator", name)
    data = OmegaConf.to_container(OmegaConf.load(path), resolve=True)
    assert isinstance(data, dict)
    data.update(overrides)
    return ActuatorParams.from_mapping(data)
