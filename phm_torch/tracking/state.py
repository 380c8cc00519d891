"""Per-actuator tracker state on disk, for resumable fleet runs.

One file per actuator, ``<state_dir>/<actuator>.pt``, written atomically (:func:`~phm_torch.io.atomic.atomic_open`)
with ``torch.save`` and read with ``torch.load(weights_only=True)`` (tensors, strings and numbers only: no
unpickling of arbitrary objects). It holds the particles (:meth:`Tracker.state`), the JSON of the inspections
reported so far, and a fingerprint of what produced them (pipeline, settings, the index rows): a state whose
fingerprint differs from the run's is ignored and recomputed.
"""

from __future__ import annotations

import hashlib
import json
import os
import re
from pathlib import Path
from typing import Any

import torch

from ..io.atomic import atomic_open

SAFE = re.compile(r"[^A-Za-z0-9_.-]")


def fingerprint(data: Any) -> str:
    """sha256 of the canonical JSON of ``data``."""
    return hashlib.sha256(json.dumps(data, sort_keys=True, default=str).encode()).hexdigest()


def state_path(state_dir: str | os.PathLike, actuator: str) -> Path:
    """The state file of one actuator (its id made file-safe, with a hash when that changed it)."""
    safe = SAFE.sub("_", actuator)
    if safe != actuator:
        safe += "-" + hashlib.sha256(actuator.encode()).hexdigest()[:8]
    return Path(state_dir) / f"{safe}.pt"


def save_state(
    state_dir: str | os.PathLike,
    actuator: str,
    key: str,
    particles: dict[str, torch.Tensor],
    inspections: list[dict[str, Any]],
) -> Path:
    """Write one actuator's state atomically."""
    path = state_path(state_dir, actuator)
    payload = {
        "actuator": actuator,
        "fingerprint": key,
        "inspections": json.dumps(inspections),
        **{f"particles.{name}": t for name, t in particles.items()},
    }
    with atomic_open(path, "wb") as fh:
        torch.save(payload, fh)
    return path


def load_state(
    state_dir: str | os.PathLike, actuator: str, key: str
) -> tuple[dict[str, torch.Tensor], list[dict[str, Any]]] | None:
    """(particles, inspections) of one actuator if its file exists and has fingerprint ``key``; else None."""
    path = state_path(state_dir, actuator)
    if not path.is_file():
        return None
    try:
        payload = torch.load(path, weights_only=True)
    except Exception as e:  # a foreign or damaged file: recomputed, never trusted  # noqa: BLE001
        raise ValueError(
            f"{path}: not a tracker state file ({type(e).__name__}: {e}); delete it to recompute"
        ) from None
    if payload.get("fingerprint") != key or payload.get("actuator") != actuator:
        return None
    particles = {name.split(".", 1)[1]: t for name, t in payload.items() if name.startswith("particles.")}
    return particles, json.loads(payload["inspections"])
