"""Config values into typed values and objects, each error a ``ValueError`` naming the field and the value.

The apps validate what they read from a composed config with these, and the settings dataclasses (of
:mod:`phm_torch.pipelines`, :mod:`phm_torch.workbench`) call them in ``__post_init__``, so a value is checked the same way whether it comes
from a YAML file, the command line or Python.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any

import torch
from hydra.errors import InstantiationException
from hydra.utils import instantiate


def number(value: Any, name: str, minimum: float | None = None, strict: bool = False) -> float:
    """A finite float from a config value, optionally bounded below (``strict``: > minimum)."""
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise ValueError(f"{name} must be a number, got {value!r}")
    value = float(value)
    if not math.isfinite(value):
        raise ValueError(f"{name} must be finite, got {value!r}")
    if minimum is not None and (value <= minimum if strict else value < minimum):
        raise ValueError(f"{name} must be {'>' if strict else '>='} {minimum:g}, got {value!r}")
    return value


def integer(value: Any, name: str, minimum: int | None = None) -> int:
    """An int from a config value (no bools, no fractional floats)."""
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


def device(value: Any) -> torch.device:
    """A torch device from its name; CUDA only where it is available."""
    try:
        dev = torch.device(str(value))
    except RuntimeError as e:
        raise ValueError(f"device: invalid device {value!r} ({e})") from None
    if dev.type == "cuda" and not torch.cuda.is_available():
        raise ValueError(f"device={value!r} but CUDA is not available on this machine; use device=cpu")
    return dev


def build(node: Any, name: str, **kwargs: Any) -> Any:
    """Instantiate a config node (its ``_target_``), passing ``kwargs`` (objects, not config) to the
    constructor; a constructor error is reported as a ValueError starting with ``name``."""
    try:
        return instantiate(node, _partial_=True)(**kwargs)
    except (InstantiationException, TypeError, ValueError) as e:
        cause = e.__cause__ if isinstance(e, InstantiationException) and e.__cause__ is not None else e
        msg = str(cause)
        raise ValueError(msg if msg.startswith(name) else f"{name}: {msg}") from None
