"""Aerodynamic hinge moment on the control surface."""

from __future__ import annotations

from typing import ClassVar

import torch

from .base import Effect, EffectContext, EffectParam, register_effect


@register_effect
class AeroHingeLoad(Effect):
    """User-side load torque K_h theta_u + M_0 opposing positive motion (a restoring hinge moment)."""

    name = "aero_hinge_load"
    PARAMS: ClassVar[dict[str, EffectParam]] = {
        "stiffness": EffectParam(
            1000.0, "N m/rad", "aerodynamic hinge stiffness K_h, user side", None, 0.02, "output_stiffness"
        ),
        "bias": EffectParam(
            1.0, "N m", "constant hinge moment M_0 (trim load), user side", None, 1 / 240, "peak_user_torque"
        ),
    }
    STRENGTH = ("stiffness", "bias")
    explains = "current error in phase with the surface position plus a constant offset (load torque / (N k_t))"

    def load_torque(self, ctx: EffectContext) -> torch.Tensor:
        return self.values["stiffness"] * ctx.theta_u + self.values["bias"]
