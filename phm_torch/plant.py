"""Per-sample physical parameters of a batch of actuators, as tensors.

A :class:`Plant` holds every continuous datasheet value as a (B,) tensor so that faults, effects and
calibration (which multiplies chosen parameters by learnable scales) all act on the same record,
differentiably. Structural integers (pole pairs, slots) and the timing rates stay in ``params``.
The record is frozen: faults, scales and effects each return a new one (``dataclasses.replace``), so a
plant handed to a function comes back as it went in.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, fields, replace

import torch

from .faults import apply_faults, as_fault_tensor
from .params import ActuatorParams, LFShape

# Fields that define the discretisation or the topology; they are not per-sample tensors.
STRUCTURAL = (
    "pole_pairs",
    "stator_slots",
    "pwm_frequency",
    "sample_rate",
    "filter_cutoff",
    "short_circuit_max",
    "nominal_faults",
    "lf_shape",
    "pinion_teeth",
)
TENSOR_FIELDS = tuple(f.name for f in fields(ActuatorParams) if f.name not in STRUCTURAL)
LF_FIELDS = tuple(f"lf_{f.name}" for f in fields(LFShape))


@dataclass(frozen=True, eq=False)
class Plant:
    """Per-sample parameters of B actuators, SI units.

    ``params`` is the datasheet the plant was built from (structural values: pole pairs, slots, rates).
    Every other field is a tensor of one dtype and device, batch first:

    - the datasheet's continuous values, named and in the units of :class:`ActuatorParams`, each (B,),
      after calibration scales, faults and effects;
    - the LF shape-function coefficients ``lf_<name>`` of :class:`LFShape`, each (B,) (per sample so that a
      fit can batch candidate values);
    - the faulted per-phase values, each (B, 3) for phases a, b, c: ``short`` the shorted-turn fraction
      s [-], ``resistance`` R (1 - s) [ohm], ``inductance`` L (1 - s)^2 [H], ``emf`` k_e (1 - s) [V s/rad];
    - the rotor eccentricity ``eccentricity`` eps [-] and its phase ``ecc_phase`` phi [rad], each (B,).

    The per-phase and eccentricity fields are derived by :func:`~phm_torch.faults.apply_faults` from the
    (B,) values; :meth:`nominal` fills them with a healthy motor's.
    """

    params: ActuatorParams
    supply_voltage: torch.Tensor
    phase_resistance: torch.Tensor
    phase_inductance: torch.Tensor
    back_emf_constant: torch.Tensor
    motor_inertia: torch.Tensor
    motor_viscous: torch.Tensor
    coulomb_friction: torch.Tensor
    static_friction: torch.Tensor
    gear_ratio: torch.Tensor
    output_stiffness: torch.Tensor
    output_damping: torch.Tensor
    backlash: torch.Tensor
    user_inertia: torch.Tensor
    user_damping: torch.Tensor
    end_stop_angle: torch.Tensor
    end_stop_stiffness: torch.Tensor
    end_stop_damping: torch.Tensor
    position_gain: torch.Tensor
    speed_limit: torch.Tensor
    speed_gain: torch.Tensor
    speed_integral_gain: torch.Tensor
    current_limit: torch.Tensor
    current_gain: torch.Tensor
    current_integral_gain: torch.Tensor
    lvdt_time_constant: torch.Tensor
    lf_emf_short_gain: torch.Tensor
    lf_resistance_short_gain: torch.Tensor
    lf_inductance_short_exponent: torch.Tensor
    lf_commutation_width: torch.Tensor
    short: torch.Tensor
    resistance: torch.Tensor
    inductance: torch.Tensor
    emf: torch.Tensor
    eccentricity: torch.Tensor
    ecc_phase: torch.Tensor

    @classmethod
    def nominal(cls, params: ActuatorParams, batch: int, dtype: torch.dtype, device: str | torch.device) -> Plant:
        """B copies of the datasheet's values, healthy (no shorted turn, no eccentricity)."""

        def full(value: float) -> torch.Tensor:
            return torch.full((batch,), float(value), dtype=dtype, device=device)

        values = {name: full(getattr(params, name)) for name in TENSOR_FIELDS}
        values.update({f"lf_{f.name}": full(getattr(params.lf_shape, f.name)) for f in fields(LFShape)})
        zero3 = torch.zeros(batch, 3, dtype=dtype, device=device)
        values.update(
            short=zero3,
            resistance=values["phase_resistance"].unsqueeze(-1) + zero3,
            inductance=values["phase_inductance"].unsqueeze(-1) + zero3,
            emf=values["back_emf_constant"].unsqueeze(-1) + zero3,
            eccentricity=full(0.0),
            ecc_phase=full(0.0),
        )
        return cls(params=params, **values)

    @property
    def batch(self) -> int:
        """Number of actuators B."""
        return self.phase_resistance.shape[0]

    @property
    def pole_pairs_f(self) -> float:
        """Pole pairs p as a float (electrical angle = p * motor angle)."""
        return float(self.params.pole_pairs)

    def to_dict(self) -> dict[str, torch.Tensor]:
        """All tensor fields by name, for inspection and tests."""
        return {f.name: getattr(self, f.name) for f in fields(self) if f.name != "params"}


def build_plant(
    params: ActuatorParams, faults: torch.Tensor, scales: Mapping[str, torch.Tensor] | None = None
) -> Plant:
    """Nominal parameters, times optional ``scales`` (calibration), then the faults.

    ``scales`` may also name the LF shape coefficients as ``lf_<coefficient>`` (values replace, not
    multiply, since some are zero by default).

    Args:
        params: the actuator datasheet.
        faults: (B, 8) fault vectors in [0, 1].
        scales: optional {field: scalar or (B,) tensor} multipliers on nominal values, e.g. the free
            parameters of a calibration; they may require grad.
    """
    k = as_fault_tensor(
        faults,
        dtype=faults.dtype if torch.is_tensor(faults) else torch.float64,
        device=faults.device if torch.is_tensor(faults) else "cpu",
    )
    plant = Plant.nominal(params, k.shape[0], k.dtype, k.device)
    changes: dict[str, torch.Tensor] = {}
    for name, scale in (scales or {}).items():
        if name in LF_FIELDS:
            value = torch.as_tensor(scale, dtype=k.dtype, device=k.device)
            if not torch.isfinite(value).all():
                raise ValueError(f"scales.{name} must be finite, got {value.detach().cpu().tolist()}")
            changes[name] = getattr(plant, name) * 0 + value
            continue
        if name not in TENSOR_FIELDS:
            raise ValueError(f"scales: unknown parameter {name!r}; known: {list(TENSOR_FIELDS)}")
        scale = torch.as_tensor(scale, dtype=k.dtype, device=k.device)
        if not torch.isfinite(scale).all() or (scale <= 0).any():
            raise ValueError(f"scales.{name} must be finite and > 0, got {scale.detach().cpu().tolist()}")
        changes[name] = getattr(plant, name) * scale
    return apply_faults(replace(plant, **changes), k, params.short_circuit_max)
