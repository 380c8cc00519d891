"""Dataset generation: fault vectors, HF signals and health labels, chunked, resumable and shardable.

The rows of every split are laid end to end in one global list (``nominal`` (1 row, k_0), ``train``,
``val``, ``rul``) and cut into chunks of ``chunk_size`` rows; chunk c is computed by shard
``c % shard_count``. A chunk is one fixed-size batch (the last one padded with k_0 rows, dropped before
writing), so a compiled simulator is compiled once per process, and a chunk's content depends only on
the config: whatever the sharding, the interruptions and the order, the chunks and hence the merged
store and its manifest are identical.

The optional assessment-only ``labels`` split (``dataset.n_labels`` rows, no signals: extra labelled
fault vectors for the health classifier) has its own row list and chunks (``labels.py``), computed and
verified by the same functions (a ``Plan`` carries its ``ChunkLayout``) and merged with the others.
"""

from __future__ import annotations

import logging
import math
import shutil
import sys
import time
import uuid
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
from tqdm import tqdm

from ..assessment import AssessmentFunction
from ..params import ActuatorParams
from ..simulator import EMASimulator
from . import randomization
from .sampling import ImportanceSampler
from .spec import DatasetSpec
from .store import (
    CHUNK_DIR,
    DATASET_FILE,
    MANIFEST_FILE,
    SIGNAL_CHUNKS,
    STORE_FILE,
    ChunkLayout,
    CorruptChunkError,
    chunk_path,
    read_chunk,
    read_json,
    write_chunk,
    write_json,
)

log = logging.getLogger(__name__)

STREAMS = (
    "train",
    "val",
    "rul",
    "labels",
    "randomize",
    "pilot",
    "life",
)  # child i of SeedSequence(seed) seeds STREAMS[i]
STAGES = ("all", "chunks", "merge")


def seed_streams(seed: int) -> dict[str, np.random.SeedSequence]:
    """The independent seed stream of each sampled split: children of ``SeedSequence(seed)`` in
    ``STREAMS`` order (``spawn(n + 1)``'s first n children are ``spawn(n)``'s: adding the labels and the
    randomize streams left the earlier ones unchanged)."""
    if isinstance(seed, bool) or not isinstance(seed, int) or seed < 0:
        raise ValueError(f"seed must be an integer >= 0, got {seed!r}")
    return dict(zip(STREAMS, np.random.SeedSequence(seed).spawn(len(STREAMS))))


def seed_record(streams: Mapping[str, np.random.SeedSequence]) -> dict[str, Any]:
    """JSON-able record of seed streams (entropy and spawn key of each)."""
    return {name: {"entropy": int(s.entropy), "spawn_key": list(s.spawn_key)} for name, s in streams.items()}


@dataclass
class Plan:
    """A row list cut into chunks: K (N, 8), the split of every row, the chunk boundaries, and the kind
    of chunk file (``SIGNAL_CHUNKS``: signals and phi_a; ``LABEL_CHUNKS``: phi_a only)."""

    K: np.ndarray
    offsets: dict[str, tuple[int, int]]  # split -> [start, stop) rows of the global list
    chunk_size: int
    seeds: dict[str, Any]
    layout: ChunkLayout = SIGNAL_CHUNKS
    effect_values: np.ndarray | None = None  # (N, P) randomised effect parameters (NaN: not randomised)

    @property
    def n_rows(self) -> int:
        return int(self.K.shape[0])

    @property
    def n_chunks(self) -> int:
        return math.ceil(self.n_rows / self.chunk_size)

    def rows(self, chunk: int) -> tuple[int, int]:
        return chunk * self.chunk_size, min((chunk + 1) * self.chunk_size, self.n_rows)


def make_plan(
    spec: DatasetSpec, nominal: Sequence[float], seed: int, sampling: Mapping[str, Any] | None = None
) -> Plan:
    """Sample every signal split (seeds spawned from ``seed``: one independent stream per split); train and
    val with the calibrated ``sampling`` record (``calibration.py``; None = the paper's scaling), rul with the
    paper's scaling on its restricted domain (near-nominal actuators whatever the calibration)."""
    streams = {name: s for name, s in seed_streams(seed).items() if name in spec.counts}
    full = ImportanceSampler.from_record(sampling, nominal, spec.uniform)
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
    k = np.concatenate(blocks)
    values = None
    if spec.randomized:
        streams["randomize"] = seed_streams(seed)["randomize"]
        values = randomization.plan_values(spec.randomized, k.shape[0], offsets["train"], streams["randomize"])
    return Plan(k, offsets, spec.chunk_size, seed_record(streams), effect_values=values)


class ChunkComputer:
    """Computes the arrays of one chunk: HF (or LF) signals on the test command, then phi_a."""

    def __init__(
        self,
        params: ActuatorParams,
        command: Callable[[torch.Tensor], torch.Tensor],
        duration: float,
        spec: DatasetSpec,
        assessment: AssessmentFunction,
        device: str | torch.device = "cpu",
    ):
        self.spec = spec
        self.command, self.duration = command, duration
        self.assessment = assessment
        self.sim = EMASimulator(
            params,
            spec.fidelity,
            substeps=spec.substeps,
            device=device,
            compile=spec.compile,
            effects=randomization.simulator_effects(spec.effects, spec.randomized),
        )
        self.base_values = randomization.base_values(self.sim.effects, spec.randomized)
        self.nominal = np.asarray(params.nominal_faults, dtype=np.float64)
        self.timing = {"signals_s": 0.0, "assessment_s": 0.0}

    def __call__(self, k: np.ndarray, effect_values: np.ndarray | None = None) -> dict[str, np.ndarray]:
        """Arrays of the chunk of fault vectors k (m, 8); ``effect_values`` (m, P): the randomised effect
        parameters of its records (``Plan.effect_values``; required when the spec randomises)."""
        m = k.shape[0]
        if self.spec.randomized:
            randomization.set_values(
                self.sim.effects, self.spec.randomized, effect_values, m, self.base_values, self.spec.chunk_size
            )
        pad = np.repeat(self.nominal[None], self.spec.chunk_size - m, axis=0)
        kt = torch.as_tensor(np.concatenate([k, pad]), dtype=torch.float64)
        t0 = time.perf_counter()
        with torch.no_grad():
            sig = self.sim.run(
                kt, self.command, self.duration, channels=["current", "position"], out_dtype=torch.float32
            )
        t1 = time.perf_counter()
        res = self.assessment(kt)
        t2 = time.perf_counter()
        self.timing["signals_s"] += t1 - t0
        self.timing["assessment_s"] += t2 - t1
        return {
            "K": k.astype(np.float64),
            "current": sig["current"][:m].numpy(),
            "position": sig["position"][:m].numpy(),
            "healthy": res.healthy[:m].numpy().astype(np.uint8),
            "margins": res.margins.stacked()[:m].numpy(),
        }


def check_writable(data_dir: Path) -> None:
    """Create ``data_dir`` and check that files can be created in it (ValueError naming it otherwise)."""
    try:
        data_dir.mkdir(parents=True, exist_ok=True)
        # unique across the nodes of a cluster sharing data_dir (a pid alone repeats from node to node)
        probe = data_dir / f".write_test.{uuid.uuid4().hex}"
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
            raise ValueError(
                f"data_dir {str(data_dir)!r} holds a store made with a different config "
                f"(fingerprint {old!r}, this config {fingerprint!r}); choose another data_dir "
                "or pass overwrite=true to delete it and start over"
            )
        log.warning("overwrite=true: deleting the store in %s", data_dir)
        for name in (MANIFEST_FILE, DATASET_FILE, STORE_FILE, "sampling.json"):  # sampling.json: calibration.py
            (data_dir / name).unlink(missing_ok=True)
        shutil.rmtree(data_dir / CHUNK_DIR, ignore_errors=True)
    write_json(marker, {"fingerprint": fingerprint, "config": config})


def chunk_attrs(plan: Plan, chunk: int, fingerprint: str) -> dict[str, Any]:
    start, stop = plan.rows(chunk)
    return {"fingerprint": fingerprint, "chunk": chunk, "rows": np.array([start, stop], dtype=np.int64)}


def compute_chunks(
    data_dir: Path,
    plan: Plan,
    fingerprint: str,
    compute: Callable[[np.ndarray], dict],
    shard_index: int,
    shard_count: int,
    repair: bool,
    progress: bool,
) -> dict[str, int]:
    """Compute this shard's missing chunks (verifying the ones present).

    ``compute`` maps the K (m, 8) of a chunk to its arrays (``plan.layout.arrays``, m rows each).
    Returns counts: ``computed``, ``reused``, ``repaired`` chunks.
    """
    layout = plan.layout
    mine = [c for c in range(plan.n_chunks) if c % shard_count == shard_index]
    todo, done_rows, repaired = [], 0, 0
    for c in mine:
        path = chunk_path(data_dir, c, layout)
        for stale in path.parent.glob(f".{path.name}.*.tmp"):  # a temp file of a killed run: never data
            stale.unlink(missing_ok=True)
        if not path.exists():
            todo.append(c)
            continue
        try:
            read_chunk(path, chunk_attrs(plan, c, fingerprint), layout.arrays)
            done_rows += plan.rows(c)[1] - plan.rows(c)[0]
        except CorruptChunkError as e:
            if not repair:
                raise ValueError(f"{e}; run again with repair=true to regenerate it") from None
            log.warning("%s: regenerating", e)
            path.unlink()
            todo.append(c)
            repaired += 1
    total = sum(plan.rows(c)[1] - plan.rows(c)[0] for c in mine)
    desc = f"shard {shard_index + 1}/{shard_count}" + ("" if layout is SIGNAL_CHUNKS else f" {layout.prefix}")
    bar = tqdm(
        total=total,
        initial=done_rows,
        unit=layout.unit,
        desc=desc,
        disable=not progress,
        file=sys.stderr,
        dynamic_ncols=True,
        smoothing=0.0,
    )
    try:
        for c in todo:
            start, stop = plan.rows(c)
            arrays = (
                compute(plan.K[start:stop])
                if plan.effect_values is None
                else compute(plan.K[start:stop], plan.effect_values[start:stop])
            )
            write_chunk(chunk_path(data_dir, c, layout), arrays, chunk_attrs(plan, c, fingerprint), layout.arrays)
            bar.update(stop - start)
    finally:
        bar.close()
    return {"computed": len(todo), "reused": len(mine) - len(todo), "repaired": repaired}


def missing_chunks(data_dir: Path, plan: Plan) -> list[int]:
    return [c for c in range(plan.n_chunks) if not chunk_path(data_dir, c, plan.layout).exists()]
