"""Parameter fitting shared by the LF shape-function fit and the workbench."""

from .levenberg_marquardt import LMResult, batched_levenberg_marquardt

__all__ = ["LMResult", "batched_levenberg_marquardt"]
