"""Merging a generated store: every chunk verified, then laid into ``dataset.h5`` (atomically) with one group
per split, and ``manifest.json`` written with each split's count, healthy fraction, unmeasurable margins and
SHA-256 per array (the chunks and the plan: ``generation.py``)."""

from __future__ import annotations

import hashlib
import json
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from ..assessment import MARGIN_NAMES, unmeasurable_counts
from .generation import Plan, chunk_attrs, missing_chunks
from .store import (
    CHUNK_DIR,
    DATASET_FILE,
    MANIFEST_FILE,
    SIGNAL_CHUNKS,
    CorruptChunkError,
    atomic_h5,
    chunk_path,
    read_chunk,
    read_json,
    write_json,
)

ROWS_PER_H5_CHUNK = 1  # HDF5 chunk shape (1, n_e) of the signal arrays: a random row read reads that row only


def merge(
    data_dir: Path,
    plan: Plan,
    fingerprint: str,
    time_grid: np.ndarray,
    command: np.ndarray,
    metadata: Mapping[str, Any],
    manifest_extra: Mapping[str, Any],
    labels: Plan | None = None,
) -> dict[str, Any]:
    """Verify every chunk and merge them into ``dataset.h5`` (atomically), then write ``manifest.json``.

    ``plan``: the signal splits; ``labels``: the plan of the labels split (``labels.make_label_plan``),
    or None for a store without it.

    Raises:
        ValueError: a chunk is missing or corrupt (``repair=true`` on its shard regenerates it).
    """
    plans = [plan] if labels is None else [plan, labels]
    for p in plans:
        missing = missing_chunks(data_dir, p)
        if missing:
            raise ValueError(
                f"cannot merge: {p.layout.unit} chunks {missing} of {p.n_chunks} are missing in "
                f"{str(data_dir / CHUNK_DIR)!r}; run the shards that own them (chunk c belongs "
                "to shard c % shard.count)"
            )
    n_e = int(time_grid.shape[0])
    splits: dict[str, Any] = {}
    with atomic_h5(data_dir / DATASET_FILE) as f:
        f.attrs["metadata"] = _json(metadata)
        f.create_dataset("time", data=time_grid, track_times=False)
        f.create_dataset("command", data=command, track_times=False)
        for p in plans:
            splits.update(_merge_plan(f, data_dir, p, fingerprint, n_e))
    manifest = {
        "format": 1,
        "fingerprint": fingerprint,
        "splits": splits,
        "arrays": list(SIGNAL_CHUNKS.arrays),
        "margin_names": list(MARGIN_NAMES),
        "signal_samples": n_e,
        **manifest_extra,
    }
    write_json(data_dir / MANIFEST_FILE, manifest)
    return manifest


def _merge_plan(f: Any, data_dir: Path, plan: Plan, fingerprint: str, n_e: int) -> dict[str, Any]:
    """Create the groups of ``plan``'s splits in the open ``dataset.h5`` ``f`` and fill them from its
    verified chunks; returns the manifest entry of each split (count, healthy, SHA-256 per array)."""
    names = plan.layout.arrays
    hashes = {s: {a: hashlib.sha256() for a in names} for s in plan.offsets}
    healthy = dict.fromkeys(plan.offsets, 0)
    unmeasurable = {s: dict.fromkeys(("phase_margin", "gain_margin", "bandwidth"), 0) for s in plan.offsets}
    out = {}
    for s, (a, b) in plan.offsets.items():
        g = f.create_group(s, track_order=True)
        n = b - a
        # row-chunked signal arrays (one record per read); an empty split cannot be chunked
        chunks = (min(ROWS_PER_H5_CHUNK, n), n_e) if n else None
        shapes = {
            "K": ((n, 8), "f8", None),
            "current": ((n, n_e), "f4", chunks),
            "position": ((n, n_e), "f4", chunks),
            "healthy": ((n,), "u1", None),
            "margins": ((n, len(MARGIN_NAMES)), "f8", None),
        }
        out[s] = {
            name: g.create_dataset(name, shapes[name][0], shapes[name][1], chunks=shapes[name][2], track_times=False)
            for name in names
        }
        g.attrs["margin_names"] = list(MARGIN_NAMES)
    for c in range(plan.n_chunks):
        start, stop = plan.rows(c)
        try:
            arrays = read_chunk(chunk_path(data_dir, c, plan.layout), chunk_attrs(plan, c, fingerprint), names)
        except CorruptChunkError as e:
            raise ValueError(f"{e}; run again with repair=true to regenerate it") from None
        for s, (a, b) in plan.offsets.items():
            lo, hi = max(a, start), min(b, stop)
            if lo >= hi:
                continue
            for name in names:
                part = np.ascontiguousarray(arrays[name][lo - start : hi - start])
                out[s][name][lo - a : hi - a] = part
                hashes[s][name].update(part.tobytes())
            healthy[s] += int(arrays["healthy"][lo - start : hi - start].sum())
            for key, v in unmeasurable_counts(arrays["margins"][lo - start : hi - start]).items():
                unmeasurable[s][key] += v
    # unmeasurable: rows whose margin has no crossing on the test grid (nan; labelled faulty)
    return {
        s: {
            "count": b - a,
            "healthy": healthy[s],
            "healthy_fraction": round(healthy[s] / (b - a), 4) if b > a else None,
            "unmeasurable": unmeasurable[s],
            "sha256": {n: hashes[s][n].hexdigest() for n in names},
        }
        for s, (a, b) in plan.offsets.items()
    }


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
