"""Typed settings of the generation pipeline (:func:`~.pipeline.generate`).

:class:`GenerateSettings` checks its own values in its constructor; every error is a ``ValueError`` naming the
config field (``shard.index``, ``stage``, ``data_dir``) and the value. The values live in ``conf/generate.yaml``
and its groups (``actuator``, ``command``, ``dataset``, ``assessment``, ``damage``); ``phm-generate``
(:mod:`phm_torch.apps.generate`) builds them from the composed config.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import torch

from ...checks import integer, number
from ...data import generation as gen
from ...params import ActuatorParams

STAGES = (*gen.STAGES, "life")  # life: only the life split (no store)


@dataclass(frozen=True)
class GenerateSettings:
    """Everything the generation pipeline reads besides the injected assessment function and damage model.

    Attributes:
        params: the actuator's datasheet.  command: the test command of every signal (position [rad] of time [s];
            its ``duration`` [s] is each signal's length, checked > 0 and stored as ``duration``).
        spec: the dataset (split sizes, chunking, signal fidelity, the life split ``spec.life``).
        device: the simulators' device.  seed: seeds the Latin hypercubes (one spawned stream per split).
        data_dir: the store directory (stored resolved, ``~`` expanded).
        stage: one of :data:`STAGES` (``all``, ``chunks``, ``merge``, ``life``).
        shard_index, shard_count: this process computes the chunks c with c % shard_count == shard_index.
        overwrite: delete a store made with a different config.  repair: regenerate chunks failing their checksum.
        progress: a progress bar on stderr.
        provenance: ``{"actuator", "command"}`` records of the store.
        config: the whole composed config as plain data: recorded in the manifest, and its data-defining nodes
            fingerprinted (:func:`~.records.fingerprint`); its ``damage`` and ``assessment`` nodes are recorded
            with the life split.
    """

    params: ActuatorParams
    command: Callable[[torch.Tensor], torch.Tensor]
    spec: gen.DatasetSpec
    device: torch.device
    seed: int
    data_dir: Path
    stage: str
    shard_index: int
    shard_count: int
    overwrite: bool
    repair: bool
    progress: bool
    provenance: Mapping[str, Any]
    config: Mapping[str, Any]
    duration: float = field(init=False)

    def __post_init__(self) -> None:
        _set(self, "duration", number(getattr(self.command, "duration", None), "command.duration", 0.0, strict=True))
        _set(self, "seed", integer(self.seed, "seed", 0))
        count = integer(self.shard_count, "shard.count", 1)
        index = integer(self.shard_index, "shard.index", 0)
        if index >= count:
            raise ValueError(f"shard.index must be in [0, shard.count - 1] = [0, {count - 1}], got {index}")
        _set(self, "shard_count", count)
        _set(self, "shard_index", index)
        if self.stage not in STAGES:
            raise ValueError(f"stage must be one of {list(STAGES)}, got {self.stage!r}")
        data_dir = self.data_dir
        if not isinstance(data_dir, (str, Path)) or not str(data_dir).strip():
            raise ValueError(f"data_dir must be a directory path, got {data_dir!r}")
        _set(self, "data_dir", Path(data_dir).expanduser().resolve())
        for name in ("overwrite", "repair", "progress"):
            _set(self, name, bool(getattr(self, name)))


def _set(settings: Any, name: str, value: Any) -> None:
    """Store a checked value on a frozen settings object."""
    object.__setattr__(settings, name, value)
