"""Inverter dead time: voltage lost at every switching edge, against the current."""

from __future__ import annotations

from typing import ClassVar

import torch

from .base import Effect, EffectContext, EffectParam, register_effect


@register_effect
class InverterDeadTime(Effect):
    """Line-voltage error -2 V_dc t_d f_pwm tanh(I / I_eps) of the driven pair.

    Each of the two switching legs loses V_dc t_d per PWM period in the direction that opposes its
    current; tanh smooths the sign over I_eps (the current that discharges the switch capacitances).
    """

    name = "inverter_dead_time"
    PARAMS: ClassVar[dict[str, EffectParam]] = {
        "dead_time": EffectParam(2.0e-6, "s", "dead time t_d per switching edge", 0.0, 0.02, "pwm_period"),
        "current_scale": EffectParam(
            0.1, "A", "current I_eps over which the error changes sign", 1.0e-6, 1 / 150, "current_limit"
        ),
    }
    STRENGTH = ("dead_time",)
    explains = (
        "voltage (current-loop integrator) offset against the sign of the current, "
        "current distortion at current zero crossings"
    )

    def voltage_error(self, ctx: EffectContext) -> torch.Tensor:
        plant = ctx.plant
        amp = 2.0 * plant.supply_voltage * self.values["dead_time"] * plant.params.pwm_frequency
        return -amp * torch.tanh(ctx.current / self.values["current_scale"])
