"""Library of optional physical effects; importing it registers every built-in effect."""

from .base import EFFECTS, Effect, EffectContext, EffectParam, build_effects, register_effect

__all__ = ["EFFECTS", "Effect", "EffectContext", "EffectParam", "build_effects", "register_effect"]
