"""Sample-time selectors: which n_points of the n_e samples of a signal to store and process."""

from .base import Selector
from .greedy import GreedySelector
from .min_error import MinErrorSelector
from .qdeim import QDEIMSelector, qr_pivots
from .random import RandomSelector
from .registry import SELECTORS, build_selector
from .som import SOMSelector
from .uniform import UniformSelector

__all__ = [
    "SELECTORS",
    "GreedySelector",
    "MinErrorSelector",
    "QDEIMSelector",
    "RandomSelector",
    "SOMSelector",
    "Selector",
    "UniformSelector",
    "build_selector",
    "qr_pivots",
]
