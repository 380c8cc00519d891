"""Model-vs-measurement workbench: calibrate a model on measurement CSVs, compare, locate where it fails, rank the
missing physical effect by score tests, add it and watch the error fall; a neural closure when no library effect
explains the residual. Entry point: :class:`Workbench` (``run`` does the whole loop) and ``phm-workbench``.
"""

from .calibrate import Calibration, FitSettings
from .candidates import Candidate, ScoreSettings
from .closure import ClosureSettings
from .closure_net import ClosureNet, NeuralClosure
from .data import Record, load_records, record_from_measurement
from .diagnostics import DiagnosticSettings
from .loop import Workbench
from .noise import HighBandNoise
from .parameters import ParameterSpace, build_space
from .report import report_dict, write_report
from .result import WorkbenchResult
from .settings import RefitSettings, WorkbenchSettings
from .synthetic import Case, synthesize

__all__ = [
    "Calibration",
    "Candidate",
    "Case",
    "ClosureNet",
    "ClosureSettings",
    "DiagnosticSettings",
    "FitSettings",
    "HighBandNoise",
    "NeuralClosure",
    "ParameterSpace",
    "Record",
    "RefitSettings",
    "ScoreSettings",
    "Workbench",
    "WorkbenchResult",
    "WorkbenchSettings",
    "build_space",
    "load_records",
    "record_from_measurement",
    "report_dict",
    "synthesize",
    "write_report",
]
