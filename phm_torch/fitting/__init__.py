"""Parameter fitting shared by the LF shape-function fit and the workbench."""

from .levenberg_marquardt import Evaluate, FitResult, Problem, fit, from_residuals

__all__ = ["Evaluate", "FitResult", "Problem", "fit", "from_residuals"]
