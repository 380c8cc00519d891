"""Prognostics: damage propagation and remaining useful life."""

from .damage import DamageModel
from .rul import DeterministicRUL, RULEstimate, RULEstimator

__all__ = ["DamageModel", "DeterministicRUL", "RULEstimate", "RULEstimator"]
