"""Cogging (detent) torque of the permanent-magnet motor."""

from __future__ import annotations

import math
from typing import ClassVar

import torch

from .base import Effect, EffectContext, EffectParam, register_effect


def cogging_periods(plant) -> int:
    """Cogging periods per mechanical revolution: lcm(Z_s, 2p) (= Z_s = 24 for the reference motor)."""
    return math.lcm(int(plant.params.stator_slots), 2 * int(plant.params.pole_pairs))


@register_effect
class CoggingTorque(Effect):
    """Torque -A sin(Z theta_m + phase) on the motor shaft, Z = lcm(Z_s, 2p) periods per revolution.

    Z is read from the plant (stator slots and pole pairs); for the usual slot/pole combinations where
    2p divides Z_s (the reference 24 slots / 8 poles) it is the slot number Z_s.
    """

    name = "cogging_torque"
    PARAMS: ClassVar[dict[str, EffectParam]] = {
        "amplitude": EffectParam(
            4.0e-3, "N m", "cogging torque amplitude A, motor side", 0.0, 1 / 300, "peak_motor_torque"
        ),
        "phase": EffectParam(0.0, "rad", "phase of the cogging wave at theta_m = 0", None, math.pi),
    }
    STRENGTH = ("amplitude",)
    explains = "current error periodic in rotor angle at the cogging order (lcm(Z_s, 2p) periods per revolution)"

    def motor_torque(self, ctx: EffectContext) -> torch.Tensor:
        z = float(cogging_periods(ctx.plant))
        return -self.values["amplitude"] * torch.sin(z * ctx.theta_m + self.values["phase"])
