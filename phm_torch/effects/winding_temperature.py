"""Winding/magnet temperature rise: copper resistance up, magnet flux (back-EMF constant) down."""

from __future__ import annotations

from dataclasses import replace
from typing import TYPE_CHECKING, ClassVar

import torch

from .base import Effect, EffectParam, register_effect

if TYPE_CHECKING:
    from ..plant import Plant


def _per_phase(factor: torch.Tensor) -> torch.Tensor:
    """Broadcast a scalar or (B,) factor against (B, 3) per-phase tensors."""
    return factor.unsqueeze(-1) if factor.ndim else factor


@register_effect
class WindingTemperature(Effect):
    """R -> R (1 + alpha_cu dT), k_e -> k_e (1 + alpha_m dT) for the scalar and the per-phase values."""

    name = "winding_temperature"
    PARAMS: ClassVar[dict[str, EffectParam]] = {
        "temperature_rise": EffectParam(40.0, "K", "temperature rise dT above the datasheet reference", -100.0, 40.0),
        "alpha_copper": EffectParam(3.93e-3, "1/K", "resistance temperature coefficient of copper", 0.0, 3.93e-3),
        "alpha_magnet": EffectParam(-1.2e-3, "1/K", "remanence temperature coefficient of the magnets", None, 1.2e-3),
    }
    STRENGTH = ("temperature_rise",)
    explains = "current and current-loop voltage scale with load: higher copper losses, lower torque per ampere"

    def modify_plant(self, plant: Plant) -> Plant:
        dt = self.values["temperature_rise"]
        r = 1.0 + self.values["alpha_copper"] * dt
        k = 1.0 + self.values["alpha_magnet"] * dt
        return replace(
            plant,
            phase_resistance=plant.phase_resistance * r,
            back_emf_constant=plant.back_emf_constant * k,
            resistance=plant.resistance * _per_phase(r),
            emf=plant.emf * _per_phase(k),
        )
