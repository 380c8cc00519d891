"""Selector registry: config names to classes."""

from __future__ import annotations

from typing import Any

from .base import Selector
from .greedy import GreedySelector
from .min_error import MinErrorSelector
from .qdeim import QDEIMSelector
from .random import RandomSelector
from .som import SOMSelector
from .uniform import UniformSelector

SELECTORS: dict[str, type[Selector]] = {
    cls.name: cls
    for cls in (SOMSelector, QDEIMSelector, GreedySelector, MinErrorSelector, UniformSelector, RandomSelector)
}


def build_selector(name: str, **params: Any) -> Selector:
    """The selector registered as ``name``, constructed with ``params``."""
    if name not in SELECTORS:
        raise ValueError(f"selector: unknown name {name!r}; known: {sorted(SELECTORS)}")
    return SELECTORS[name](**params)
