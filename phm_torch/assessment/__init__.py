"""Health assessment of an actuator from its LF frequency response (ema_reference.md §4)."""

from .design import SweepDesign
from .frequency_response import FrequencyResponse
from .health import Assessment, AssessmentFunction, HealthRequirements
from .linear import LinearLoop, linear_loop
from .margins import MARGIN_NAMES, Margins, margins, unmeasurable_counts
from .readings import LoopResponse
from .sweep import SineSweep

__all__ = [
    "MARGIN_NAMES",
    "Assessment",
    "AssessmentFunction",
    "FrequencyResponse",
    "HealthRequirements",
    "LinearLoop",
    "LoopResponse",
    "Margins",
    "SineSweep",
    "SweepDesign",
    "linear_loop",
    "margins",
    "unmeasurable_counts",
]
