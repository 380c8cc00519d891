"""Checks of the workbench's settings values: each returns the value as the settings keep it (``float``,
``int``, ``tuple``) or raises a ``ValueError`` naming the field (its config path, e.g. ``score.alpha``) and
the value. The settings dataclasses call them in ``__post_init__``, so a value is checked the same way
whether it comes from ``conf/workbench.yaml``, the command line or Python.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any


def number(
    value: Any, name: str, minimum: float | None = None, strict: bool = False, maximum: float | None = None
) -> float:
    """A finite float, optionally >= ``minimum`` (> with ``strict``) and < ``maximum``."""
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise ValueError(f"{name} must be a finite number, got {value!r}")
    if minimum is not None and (value <= minimum if strict else value < minimum):
        raise ValueError(f"{name} must be {'>' if strict else '>='} {minimum:g}, got {value!r}")
    if maximum is not None and not value < maximum:
        raise ValueError(f"{name} must be < {maximum:g}, got {value!r}")
    return float(value)


def integer(value: Any, name: str, minimum: int | None = None) -> int:
    """An int (no bool, no float), optionally >= ``minimum``."""
    if isinstance(value, bool) or not isinstance(value, int):
        raise ValueError(f"{name} must be an integer, got {value!r}")
    if minimum is not None and value < minimum:
        raise ValueError(f"{name} must be >= {minimum}, got {value!r}")
    return int(value)


def numbers(value: Any, name: str, minimum: float | None = None, strict: bool = False) -> tuple[float, ...]:
    """A non-empty sequence of numbers (each checked as :func:`number`) as a tuple."""
    if isinstance(value, (str, bytes, Mapping)) or not hasattr(value, "__len__") or not len(value):
        raise ValueError(f"{name} must be a non-empty list of numbers, got {value!r}")
    return tuple(number(v, f"{name}[{i}]", minimum, strict) for i, v in enumerate(value))


def names(value: Any, name: str) -> tuple[str, ...]:
    """A sequence of non-empty strings (one string is a list of one) as a tuple."""
    if isinstance(value, str):
        value = [value]
    if (
        isinstance(value, (bytes, Mapping))
        or not hasattr(value, "__iter__")
        or not all(isinstance(v, str) and v for v in value)
    ):
        raise ValueError(f"{name} must be a list of names, got {value!r}")
    return tuple(value)


def mapping(value: Any, name: str) -> dict:
    """A mapping as a dict (``None``: empty)."""
    if value is None:
        return {}
    if not isinstance(value, Mapping):
        raise ValueError(f"{name} must be a mapping, got {value!r}")
    return dict(value)


def flag(value: Any, name: str) -> bool:
    """A bool (no 0/1, no string)."""
    if not isinstance(value, bool):
        raise ValueError(f"{name} must be true or false, got {value!r}")
    return value
