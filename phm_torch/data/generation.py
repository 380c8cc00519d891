"""Dataset generation: fault vectors, HF signals and health labels, chunked, resumable and shardable.

The rows of every split are laid end to end in one global list (``nominal`` (1 row, k_0), ``train``,
``val``, ``rul``) and cut into chunks of ``chunk_size`` rows; chunk c is computed by shard
``c % shard_count``. A chunk is one fixed-size batch (the last one padded with k_0 rows, dropped before
writing), so a compiled simulator is compiled once per process, and a chunk's content depends only on
the config: whatever the sharding, the interruptions and the order, the chunks and hence the merged
store and its manifest are identical.
"""

from __future__ import annotations

import hashlib
import json
import logging
import math
import os
import shutil
import sys
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch
from tqdm import tqdm

from ..assessment import MARGIN_NAMES, AssessmentFunction
from ..params import ActuatorParams
from ..simulator import EMASimulator
from .sampling import ImportanceSampler
from .store import (
    ARRAYS,
    CHUNK_DIR,
    DATASET_FILE,
    MANIFEST_FILE,
    STORE_FILE,
    CorruptChunkError,
    atomic_h5,
    chunk_path,
    read_chunk,
    read_json,
    write_chunk,
    write_json,
)

log = logging.getLogger(__name__)

SPLITS = ("nominal", "train", "val", "rul")
STAGES = ("all", "chunks", "merge")
ROWS_PER_H5_CHUNK = 1    # HDF5 chunk shape (1, n_e) of the signal arrays: a random row read reads that row only


@dataclass(frozen=True)
class DatasetSpec:
    """What to generate.

    Attributes:
        n_train, n_val: rows of the importance-sampled splits (full domain).
        n_rul: rows of the RUL split, importance-sampled on the restricted domain of normalised
            L-infinity radius ``rul_radius`` about nominal (mostly healthy actuators).
        uniform: 0-based fault indices left uniform by the sampling (k7, eccentricity phase -> 6).
        chunk_size: rows per chunk = simulator batch size.
        fidelity: model producing the signals (``hf``; ``lf`` for quick tests).
        compile: compile the signal simulator (pays ~15-30 s once per process).
        substeps: simulator substeps per control period (null: the fidelity's default).
    """

    n_train: int
    n_val: int
    n_rul: int
    rul_radius: float
    uniform: tuple[int, ...]
    chunk_size: int
    fidelity: str
    compile: bool
    substeps: int | None = field(default=None)

    def __post_init__(self) -> None:
        object.__setattr__(self, "uniform", tuple(int(i) for i in self.uniform))
        for name, low in (("n_train", 1), ("n_val", 0), ("n_rul", 0), ("chunk_size", 1)):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int) or v < low:
                raise ValueError(f"dataset.{name} must be an integer >= {low}, got {v!r}")
        if not (isinstance(self.rul_radius, (int, float)) and 0 < self.rul_radius <= 1):
            raise ValueError(f"dataset.rul_radius must be in (0, 1], got {self.rul_radius!r}")
        if self.fidelity not in ("hf", "lf"):
            raise ValueError(f"dataset.fidelity must be 'hf' or 'lf', got {self.fidelity!r}")
        if self.substeps is not None and (not isinstance(self.substeps, int) or self.substeps < 1):
            raise ValueError(f"dataset.substeps must be null or an integer >= 1, got {self.substeps!r}")

    @property
    def counts(self) -> dict[str, int]:
        return {"nominal": 1, "train": self.n_train, "val": self.n_val, "rul": self.n_rul}


@dataclass
class Plan:
    """The global row list: K (N, 8), the split of every row, and the chunk boundaries."""

    K: np.ndarray
    offsets: dict[str, tuple[int, int]]   # split -> [start, stop) rows of the global list
    chunk_size: int
    seeds: dict[str, Any]

    @property
    def n_rows(self) -> int:
        return int(self.K.shape[0])

    @property
    def n_chunks(self) -> int:
        return math.ceil(self.n_rows / self.chunk_size)

    def rows(self, chunk: int) -> tuple[int, int]:
        return chunk * self.chunk_size, min((chunk + 1) * self.chunk_size, self.n_rows)


def make_plan(spec: DatasetSpec, nominal: Sequence[float], seed: int) -> Plan:
    """Sample every split (seeds spawned from ``seed``: one independent stream per split)."""
    if isinstance(seed, bool) or not isinstance(seed, int) or seed < 0:
        raise ValueError(f"seed must be an integer >= 0, got {seed!r}")
    streams = dict(zip(("train", "val", "rul"), np.random.SeedSequence(seed).spawn(3)))
    full = ImportanceSampler(tuple(nominal), spec.uniform, 1.0)
    near = ImportanceSampler(tuple(nominal), spec.uniform, float(spec.rul_radius))
    blocks, offsets, start = [], {}, 0
    for name, n in spec.counts.items():
        if name == "nominal":
            k = np.asarray([nominal], dtype=np.float64)
        elif n == 0:
            k = np.zeros((0, len(nominal)))
        else:
            k = (near if name == "rul" else full).sample(n, streams[name])
        blocks.append(k)
        offsets[name] = (start, start + n)
        start += n
    seeds = {name: {"entropy": int(s.entropy), "spawn_key": list(s.spawn_key)} for name, s in streams.items()}
    return Plan(np.concatenate(blocks), offsets, spec.chunk_size, seeds)


class ChunkComputer:
    """Computes the arrays of one chunk: HF (or LF) signals on the test command, then phi_a."""

    def __init__(self, params: ActuatorParams, command: Callable[[torch.Tensor], torch.Tensor], duration: float,
                 spec: DatasetSpec, assessment: AssessmentFunction, device: str | torch.device = "cpu"):
        self.spec = spec
        self.command, self.duration = command, duration
        self.assessment = assessment
        self.sim = EMASimulator(params, spec.fidelity, substeps=spec.substeps, device=device, compile=spec.compile)
        self.nominal = np.asarray(params.nominal_faults, dtype=np.float64)
        self.timing = {"signals_s": 0.0, "assessment_s": 0.0}

    def __call__(self, k: np.ndarray) -> dict[str, np.ndarray]:
        m = k.shape[0]
        pad = np.repeat(self.nominal[None], self.spec.chunk_size - m, axis=0)
        kt = torch.as_tensor(np.concatenate([k, pad]), dtype=torch.float64)
        t0 = time.perf_counter()
        with torch.no_grad():
            sig = self.sim.run(kt, self.command, self.duration, channels=["current", "position"],
                               out_dtype=torch.float32)
        t1 = time.perf_counter()
        res = self.assessment(kt)
        t2 = time.perf_counter()
        self.timing["signals_s"] += t1 - t0
        self.timing["assessment_s"] += t2 - t1
        return {"K": k.astype(np.float64), "current": sig["current"][:m].numpy(),
                "position": sig["position"][:m].numpy(), "healthy": res.healthy[:m].numpy().astype(np.uint8),
                "margins": res.margins.stacked()[:m].numpy()}


def check_writable(data_dir: Path) -> None:
    """Create ``data_dir`` and check that files can be created in it (ValueError naming it otherwise)."""
    try:
        data_dir.mkdir(parents=True, exist_ok=True)
        probe = data_dir / f".write_test.{os.getpid()}"
        probe.write_bytes(b"")
        probe.unlink()
    except OSError as e:
        raise ValueError(f"data_dir {str(data_dir)!r} is not writable: {e.strerror or e}") from None


def prepare_store(data_dir: Path, fingerprint: str, config: Mapping[str, Any], overwrite: bool) -> None:
    """Claim ``data_dir`` for this config: refuse a store made with another config unless ``overwrite``,
    which deletes the store's files (only those: store.json, chunks/, dataset.h5, manifest.json)."""
    check_writable(data_dir)
    marker = data_dir / STORE_FILE
    if marker.is_file():
        try:
            old = read_json(marker).get("fingerprint")
        except (OSError, ValueError):
            old = None
        if old == fingerprint:
            return
        if not overwrite:
            raise ValueError(f"data_dir {str(data_dir)!r} holds a store made with a different config "
                             f"(fingerprint {old!r}, this config {fingerprint!r}); choose another data_dir "
                             "or pass overwrite=true to delete it and start over")
        log.warning("overwrite=true: deleting the store in %s", data_dir)
        for name in (MANIFEST_FILE, DATASET_FILE, STORE_FILE):
            (data_dir / name).unlink(missing_ok=True)
        shutil.rmtree(data_dir / CHUNK_DIR, ignore_errors=True)
    write_json(marker, {"fingerprint": fingerprint, "config": config})


def chunk_attrs(plan: Plan, chunk: int, fingerprint: str) -> dict[str, Any]:
    start, stop = plan.rows(chunk)
    return {"fingerprint": fingerprint, "chunk": chunk, "rows": np.array([start, stop], dtype=np.int64)}


def compute_chunks(data_dir: Path, plan: Plan, fingerprint: str, compute: Callable[[np.ndarray], dict],
                   shard_index: int, shard_count: int, repair: bool, progress: bool) -> dict[str, int]:
    """Compute this shard's missing chunks (verifying the ones present).

    Returns counts: ``computed``, ``reused``, ``repaired`` chunks.
    """
    mine = [c for c in range(plan.n_chunks) if c % shard_count == shard_index]
    todo, done_rows, repaired = [], 0, 0
    for c in mine:
        path = chunk_path(data_dir, c)
        for stale in path.parent.glob(f".{path.name}.*.tmp"):  # a temp file of a killed run: never data
            stale.unlink(missing_ok=True)
        if not path.exists():
            todo.append(c)
            continue
        try:
            read_chunk(path, chunk_attrs(plan, c, fingerprint))
            done_rows += plan.rows(c)[1] - plan.rows(c)[0]
        except CorruptChunkError as e:
            if not repair:
                raise ValueError(f"{e}; run again with repair=true to regenerate it") from None
            log.warning("%s: regenerating", e)
            path.unlink()
            todo.append(c)
            repaired += 1
    total = sum(plan.rows(c)[1] - plan.rows(c)[0] for c in mine)
    bar = tqdm(total=total, initial=done_rows, unit="signal", desc=f"shard {shard_index + 1}/{shard_count}",
               disable=not progress, file=sys.stderr, dynamic_ncols=True, smoothing=0.0)
    try:
        for c in todo:
            start, stop = plan.rows(c)
            arrays = compute(plan.K[start:stop])
            write_chunk(chunk_path(data_dir, c), arrays, chunk_attrs(plan, c, fingerprint))
            bar.update(stop - start)
    finally:
        bar.close()
    return {"computed": len(todo), "reused": len(mine) - len(todo), "repaired": repaired}


def missing_chunks(data_dir: Path, plan: Plan) -> list[int]:
    return [c for c in range(plan.n_chunks) if not chunk_path(data_dir, c).exists()]


def merge(data_dir: Path, plan: Plan, fingerprint: str, time_grid: np.ndarray, command: np.ndarray,
          metadata: Mapping[str, Any], manifest_extra: Mapping[str, Any]) -> dict[str, Any]:
    """Verify every chunk and merge them into ``dataset.h5`` (atomically), then write ``manifest.json``.

    Raises:
        ValueError: a chunk is missing or corrupt (``repair=true`` on its shard regenerates it).
    """
    missing = missing_chunks(data_dir, plan)
    if missing:
        raise ValueError(f"cannot merge: chunks {missing} of {plan.n_chunks} are missing in "
                         f"{str(data_dir / CHUNK_DIR)!r}; run the shards that own them (chunk c belongs to "
                         "shard c % shard.count)")
    n_e = int(time_grid.shape[0])
    hashes = {s: {a: hashlib.sha256() for a in ARRAYS} for s in SPLITS}
    healthy = dict.fromkeys(SPLITS, 0)
    with atomic_h5(data_dir / DATASET_FILE) as f:
        f.attrs["metadata"] = _json(metadata)
        f.create_dataset("time", data=time_grid, track_times=False)
        f.create_dataset("command", data=command, track_times=False)
        out = {}
        for s in SPLITS:
            a, b = plan.offsets[s]
            g = f.create_group(s, track_order=True)
            n = b - a
            rows = max(1, min(ROWS_PER_H5_CHUNK, n))
            out[s] = {"K": g.create_dataset("K", (n, 8), "f8", track_times=False),
                      "current": g.create_dataset("current", (n, n_e), "f4", chunks=(rows, n_e), track_times=False),
                      "position": g.create_dataset("position", (n, n_e), "f4", chunks=(rows, n_e), track_times=False),
                      "healthy": g.create_dataset("healthy", (n,), "u1", track_times=False),
                      "margins": g.create_dataset("margins", (n, len(MARGIN_NAMES)), "f8", track_times=False)}
            g.attrs["margin_names"] = list(MARGIN_NAMES)
        for c in range(plan.n_chunks):
            start, stop = plan.rows(c)
            try:
                arrays = read_chunk(chunk_path(data_dir, c), chunk_attrs(plan, c, fingerprint))
            except CorruptChunkError as e:
                raise ValueError(f"{e}; run again with repair=true to regenerate it") from None
            for s in SPLITS:
                a, b = plan.offsets[s]
                lo, hi = max(a, start), min(b, stop)
                if lo >= hi:
                    continue
                for name in ARRAYS:
                    part = np.ascontiguousarray(arrays[name][lo - start:hi - start])
                    out[s][name][lo - a:hi - a] = part
                    hashes[s][name].update(part.tobytes())
                healthy[s] += int(arrays["healthy"][lo - start:hi - start].sum())
    splits = {s: {"count": plan.offsets[s][1] - plan.offsets[s][0], "healthy": healthy[s],
                  "sha256": {a: hashes[s][a].hexdigest() for a in ARRAYS}} for s in SPLITS}
    manifest = {"format": 1, "fingerprint": fingerprint, "splits": splits, "arrays": list(ARRAYS),
                "margin_names": list(MARGIN_NAMES), "signal_samples": n_e, **manifest_extra}
    write_json(data_dir / MANIFEST_FILE, manifest)
    return manifest


def is_complete(data_dir: Path, fingerprint: str) -> bool:
    """A finished store of this config is in ``data_dir`` (manifest with this fingerprint, dataset file)."""
    manifest = data_dir / MANIFEST_FILE
    if not (manifest.is_file() and (data_dir / DATASET_FILE).is_file()):
        return False
    try:
        return read_json(manifest).get("fingerprint") == fingerprint
    except (OSError, ValueError):
        return False


def _json(data: Any) -> str:
    return json.dumps(data, sort_keys=True)
