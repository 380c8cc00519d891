"""Stribeck friction: extra dry friction at low sliding speed (boundary lubrication)."""

from __future__ import annotations

from typing import ClassVar

import torch

from .base import Effect, EffectContext, EffectParam, register_effect


@register_effect
class StribeckFriction(Effect):
    """Kinetic friction + A exp(-(omega_m / omega_s)^2) and break-away + A, motor side.

    The extra friction is a magnitude applied against the motion by the Karnopp model of
    ``physics/mechanics.py``; it equals A at rest, so the static friction rises by the same A.
    """

    name = "stribeck_friction"
    PARAMS: ClassVar[dict[str, EffectParam]] = {
        "amplitude": EffectParam(
            5.0e-3, "N m", "extra friction at zero speed, motor side", 0.0, 1 / 240, "peak_motor_torque"
        ),
        "velocity": EffectParam(5.0, "rad/s", "Stribeck velocity omega_s (motor side)", 1.0e-6, 1 / 60, "speed_limit"),
    }
    STRENGTH = ("amplitude",)
    explains = "current error concentrated at low motor speed, i.e. around velocity reversals, sign of the speed"

    def friction_torque(self, ctx: EffectContext) -> torch.Tensor:
        x = ctx.omega_m / self.values["velocity"]
        return self.values["amplitude"] * torch.exp(-x * x)

    def breakaway_torque(self, ctx: EffectContext) -> torch.Tensor:
        return self.values["amplitude"]
