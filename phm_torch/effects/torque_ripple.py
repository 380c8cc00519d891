"""Generic torque ripple periodic in the rotor angle (gear mesh, magnet or slot harmonics, a bent shaft)."""

from __future__ import annotations

import math
from typing import ClassVar

import torch

from .base import Effect, EffectContext, EffectParam, register_effect


@register_effect
class TorqueRipple(Effect):
    """Torque -A sin(h theta_m + phase) on the motor shaft, h periods per motor mechanical turn.

    Unlike :class:`~phm_torch.effects.cogging_torque.CoggingTorque`, whose order the motor's slots and poles
    fix, the order h is a parameter: a gear mesh has the pinion's tooth count, a rotor defect order 1, a
    ripple outside the named library the order the residual shows (the workbench proposes it from its
    rotor-angle harmonic analysis). h need not be an integer (a ripple of the output gear seen from the motor
    is 1/N per motor turn).
    """

    name = "torque_ripple"
    PARAMS: ClassVar[dict[str, EffectParam]] = {
        "order": EffectParam(1.0, "1/rev", "periods per motor mechanical turn h", 0.0, 10.0),
        "amplitude": EffectParam(4.0e-3, "N m", "ripple amplitude A, motor side", 0.0, 1 / 300, "peak_motor_torque"),
        "phase": EffectParam(0.0, "rad", "phase of the ripple at theta_m = 0", None, math.pi),
    }
    STRENGTH = ("amplitude",)
    explains = "current error periodic in rotor angle at one order per motor turn (the order fitted)"

    def motor_torque(self, ctx: EffectContext) -> torch.Tensor:
        v = self.values
        return -v["amplitude"] * torch.sin(v["order"] * ctx.theta_m + v["phase"])
