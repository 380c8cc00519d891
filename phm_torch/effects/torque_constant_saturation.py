"""Magnetic saturation: torque/back-EMF constant falling with the current."""

from __future__ import annotations

from typing import ClassVar

import torch

from .base import Effect, EffectContext, EffectParam, register_effect


@register_effect
class TorqueConstantSaturation(Effect):
    """k_t -> k_t / (1 + a (I / I_s)^2), I the driven-pair (HF) or DC (LF) current."""

    name = "torque_constant_saturation"
    PARAMS: ClassVar[dict[str, EffectParam]] = {
        "coefficient": EffectParam(0.3, "-", "saturation coefficient a", 0.0, 0.3),
        "current_scale": EffectParam(5.0, "A", "current scale I_s", 1.0e-6, 1 / 3, "current_limit"),
    }
    STRENGTH = ("coefficient",)
    explains = "current error growing with the square of the current (cubic in the load), largest at peak current"

    def emf_scale(self, ctx: EffectContext) -> torch.Tensor:
        x = ctx.current / self.values["current_scale"]
        return 1.0 / (1.0 + self.values["coefficient"] * x * x)
