"""Per-sample physical parameters of a batch of actuators, as tensors.

A :class:`Plant` holds every continuous datasheet value as a (B,) tensor so that faults, effects and
calibration (which multiplies chosen parameters by learnable scales) all act on the same record,
differentiably. Structural integers (pole pairs, slots) and the timing rates stay Python numbers.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import fields

import torch

from .faults import apply_faults, as_fault_tensor
from .params import ActuatorParams

# Fields that define the discretisation or the topology; they are not per-sample tensors.
STRUCTURAL = ("pole_pairs", "stator_slots", "pwm_frequency", "sample_rate", "filter_cutoff",
              "short_circuit_max", "nominal_faults", "lf_shape", "pinion_teeth")
TENSOR_FIELDS = tuple(f.name for f in fields(ActuatorParams) if f.name not in STRUCTURAL)


class Plant:
    """Per-sample parameters. Attributes named as in :class:`ActuatorParams` are (B,) tensors.

    After :func:`build_plant` it also carries the faulted per-phase tensors ``resistance`` [ohm],
    ``inductance`` [H], ``emf`` [V s/rad], ``short`` [-] (all (B, 3)) and ``eccentricity`` [-],
    ``ecc_phase`` [rad] (B,).
    """

    def __init__(self, params: ActuatorParams, batch: int, dtype: torch.dtype, device: torch.device):
        self.params = params
        self.batch = batch
        self.pole_pairs_f = float(params.pole_pairs)
        # LF shape-function coefficients, per sample so that a fit can batch candidate values.
        for f in fields(params.lf_shape):
            setattr(self, f"lf_{f.name}", torch.full((batch,), float(getattr(params.lf_shape, f.name)),
                                                     dtype=dtype, device=device))
        for name in TENSOR_FIELDS:
            setattr(self, name, torch.full((batch,), float(getattr(params, name)), dtype=dtype, device=device))

    def to_dict(self) -> dict[str, torch.Tensor]:
        """All tensor attributes, for inspection and tests."""
        return {k: v for k, v in vars(self).items() if isinstance(v, torch.Tensor)}


def build_plant(params: ActuatorParams, faults: torch.Tensor, scales: Mapping[str, torch.Tensor] | None = None
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
    k = as_fault_tensor(faults, dtype=faults.dtype if torch.is_tensor(faults) else torch.float64,
                        device=faults.device if torch.is_tensor(faults) else "cpu")
    plant = Plant(params, k.shape[0], k.dtype, k.device)
    for name, scale in (scales or {}).items():
        if name.startswith("lf_") and hasattr(plant, name):
            value = torch.as_tensor(scale, dtype=k.dtype, device=k.device)
            if not torch.isfinite(value).all():
                raise ValueError(f"scales.{name} must be finite, got {value.detach().cpu().tolist()}")
            setattr(plant, name, getattr(plant, name) * 0 + value)
            continue
        if name not in TENSOR_FIELDS:
            raise ValueError(f"scales: unknown parameter {name!r}; known: {list(TENSOR_FIELDS)}")
        scale = torch.as_tensor(scale, dtype=k.dtype, device=k.device)
        if not torch.isfinite(scale).all() or (scale <= 0).any():
            raise ValueError(f"scales.{name} must be finite and > 0, got {scale.detach().cpu().tolist()}")
        setattr(plant, name, getattr(plant, name) * scale)
    apply_faults(plant, k, params.short_circuit_max)
    return plant
