"""The evaluation pipeline (``phm-evaluate``): :func:`evaluate_rul` of :class:`EvaluateSettings`."""

from .pipeline import evaluate_rul
from .settings import CalibrationSettings, EvaluateSettings, ReferenceSettings, RULSettings

__all__ = ["CalibrationSettings", "EvaluateSettings", "RULSettings", "ReferenceSettings", "evaluate_rul"]
