"""Series compliance of the output stage (linkage, attachment, bearing deflection)."""

from __future__ import annotations

from dataclasses import replace
from typing import TYPE_CHECKING, ClassVar

from .base import Effect, EffectParam, register_effect

if TYPE_CHECKING:
    from ..plant import Plant


@register_effect
class TransmissionCompliance(Effect):
    """Compliance C in series with the output stiffness K_t: K_eff = K_t / (1 + K_t C)."""

    name = "transmission_compliance"
    PARAMS: ClassVar[dict[str, EffectParam]] = {
        "compliance": EffectParam(
            1.0e-5, "rad/(N m)", "extra series compliance C, user side", 0.0, 0.5, "output_compliance"
        ),
    }
    STRENGTH = ("compliance",)
    explains = (
        "larger gear-to-surface deflection under load and a lower output-stage resonance: "
        "position error growing with the chirp frequency"
    )

    def modify_plant(self, plant: Plant) -> Plant:
        k = plant.output_stiffness
        return replace(plant, output_stiffness=k / (1.0 + k * self.values["compliance"]))
