"""Extra motor-side viscous friction (e.g. cold gearbox lubricant, bearing drag)."""

from __future__ import annotations

from typing import ClassVar

import torch

from .base import Effect, EffectContext, EffectParam, register_effect


@register_effect
class ViscousFriction(Effect):
    """Torque -c * omega_m on the motor shaft, added to the datasheet's ``motor_viscous``.

    Implemented as a signed motor torque (not a friction magnitude) so that it is smooth through zero
    speed and linear in c.
    """

    name = "viscous_friction"
    PARAMS: ClassVar[dict[str, EffectParam]] = {
        "coefficient": EffectParam(
            1.0e-4, "N m s/rad", "extra motor-side viscous coefficient c", 0.0, 1 / 40, "motor_damping"
        ),
    }
    STRENGTH = ("coefficient",)
    explains = "current error proportional to motor speed, largest at peak speed and zero at velocity reversals"

    def motor_torque(self, ctx: EffectContext) -> torch.Tensor:
        return -self.values["coefficient"] * ctx.omega_m
