"""Extra lag of the position sensor (LVDT demodulator filter, slow acquisition)."""

from __future__ import annotations

from dataclasses import replace
from typing import TYPE_CHECKING, ClassVar

from .base import Effect, EffectParam, register_effect

if TYPE_CHECKING:
    from ..plant import Plant


@register_effect
class PositionSensorLag(Effect):
    """Adds tau to the LVDT first-order time constant."""

    name = "position_sensor_lag"
    PARAMS: ClassVar[dict[str, EffectParam]] = {
        "time_constant": EffectParam(1.0e-3, "s", "extra LVDT time constant tau", 0.0, 1.0e-3),
    }
    STRENGTH = ("time_constant",)
    explains = (
        "measured position lagging the surface by tau d(theta_u)/dt; more phase lag and resonance at high frequency"
    )

    def modify_plant(self, plant: Plant) -> Plant:
        return replace(plant, lvdt_time_constant=plant.lvdt_time_constant + self.values["time_constant"])
