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
        # typical magnitude 4 x the nominal compliance 1 / K_t: the signature is strongly nonlinear in C (the
        # resonance moves), and a probe (0.1 of it) much below 1 / K_t reads only the local slope, which the
        # sensor lag's matches (a rudder compliance of 5.7 / K_t was named a sensor lag with a 0.05 / K_t probe)
        "compliance": EffectParam(
            1.0e-5, "rad/(N m)", "extra series compliance C, user side", 0.0, 4.0, "output_compliance"
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
