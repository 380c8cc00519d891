"""The dataset store on disk: self-verifying chunk files, the merged HDF5 file, the manifest, and reads.

Layout of ``data_dir``::

    store.json             fingerprint + resolved generation config (written first; guards against mixing)
    chunks/chunk_00000.h5  rows [c * chunk_size, ...) of the global row list, one file per chunk
    dataset.h5             the merged store: one group per split (see ``ARRAYS``), written last
    manifest.json          per split: count, healthy count, SHA-256 of every array (deterministic)

Every file is written under a temporary name and renamed into place (``io/atomic.py``), so a reader
never sees a half-written file. A chunk file carries the SHA-256 of its own arrays; ``read_chunk``
recomputes it, so a damaged chunk is detected and never used as data. Arrays, per split with n rows:

* ``K`` (n, 8) float64 fault vectors;  ``current`` (n, n_e) float32 HF filtered envelope current [A];
* ``position`` (n, n_e) float32 LVDT position [rad];  ``healthy`` (n,) uint8 phi_a (1 = healthy);
* ``margins`` (n, 5) float64, columns ``MARGIN_NAMES`` (Hz, deg, Hz, dB, Hz; nan = not measurable).

The root of ``dataset.h5`` holds ``time`` (n_e,) [s] and ``command`` (n_e,) [rad], and the attribute
``metadata`` (JSON: resolved config, seeds, package version, git revision, fingerprint).
"""

from __future__ import annotations

import hashlib
import json
import os
from collections.abc import Iterator, Mapping
from contextlib import contextmanager
from pathlib import Path
from typing import Any, Self

import h5py
import numpy as np

from ..io.atomic import atomic_open

ARRAYS = ("K", "current", "position", "healthy", "margins")
DATASET_FILE = "dataset.h5"
MANIFEST_FILE = "manifest.json"
STORE_FILE = "store.json"
CHUNK_DIR = "chunks"


class CorruptChunkError(ValueError):
    """A chunk file whose content does not match its checksum (or cannot be read)."""


def array_digest(arrays: Mapping[str, np.ndarray]) -> str:
    """SHA-256 over the arrays of ``ARRAYS`` (name, dtype, shape, C-order bytes), in that order."""
    h = hashlib.sha256()
    for name in ARRAYS:
        a = np.ascontiguousarray(arrays[name])
        h.update(f"{name}|{a.dtype.str}|{a.shape}|".encode())
        h.update(a.tobytes())
    return h.hexdigest()


@contextmanager
def atomic_h5(path: Path) -> Iterator[h5py.File]:
    """An HDF5 file written under a temporary name and renamed to ``path`` only if the block succeeds."""
    with atomic_open(path, "w+b") as fh, h5py.File(fh, "w", track_order=True) as f:
        yield f


def chunk_path(data_dir: Path, index: int) -> Path:
    return Path(data_dir) / CHUNK_DIR / f"chunk_{index:05d}.h5"


def write_chunk(path: Path, arrays: Mapping[str, np.ndarray], attrs: Mapping[str, Any]) -> str:
    """Write one chunk atomically with the SHA-256 of its arrays; returns the digest."""
    digest = array_digest(arrays)
    with atomic_h5(path) as f:
        for name in ARRAYS:
            f.create_dataset(name, data=arrays[name], track_times=False)
        for key, value in attrs.items():
            f.attrs[key] = value
        f.attrs["sha256"] = digest
    return digest


def read_chunk(path: Path, expect: Mapping[str, Any]) -> dict[str, np.ndarray]:
    """Read and verify a chunk: its checksum and the attributes in ``expect`` (e.g. fingerprint, rows).

    Raises:
        CorruptChunkError: unreadable file, checksum mismatch or attribute mismatch.
    """
    try:
        with h5py.File(path, "r") as f:
            arrays = {name: f[name][()] for name in ARRAYS}
            attrs = {k: f.attrs[k] for k in f.attrs}
    except (OSError, KeyError, ValueError) as e:
        raise CorruptChunkError(f"chunk {path}: unreadable ({e})") from None
    for key, value in expect.items():
        if key not in attrs or not np.array_equal(np.asarray(attrs[key]), np.asarray(value)):
            raise CorruptChunkError(f"chunk {path}: attribute {key} is {attrs.get(key)!r}, expected {value!r}")
    digest = array_digest(arrays)
    if attrs.get("sha256") != digest:
        raise CorruptChunkError(f"chunk {path}: checksum mismatch (stored {attrs.get('sha256')!r}, "
                                f"content {digest!r})")
    return arrays


def read_json(path: Path) -> Any:
    with open(path) as fh:
        return json.load(fh)


def write_json(path: Path, data: Any) -> None:
    with atomic_open(path, "w") as fh:
        json.dump(data, fh, indent=2, sort_keys=True)
        fh.write("\n")


class SplitView:
    """Lazy view of one split of an open ``dataset.h5`` (h5py datasets: slicing reads only those rows)."""

    def __init__(self, group: h5py.Group):
        self.group = group
        for name in ARRAYS:
            setattr(self, name, group[name])

    def __len__(self) -> int:
        return int(self.group["K"].shape[0])


class DatasetStore:
    """Read access to a finished store (``dataset.h5`` + ``manifest.json``).

    Args:
        data_dir: the store directory.
        verify: recompute every array's SHA-256 against the manifest (reads everything once).

    ``store.split("train").current[10:20]`` reads rows 10..19 only. Close with ``close()`` or use
    as a context manager.
    """

    def __init__(self, data_dir: str | os.PathLike, verify: bool = False):
        self.data_dir = Path(data_dir)
        manifest, dataset = self.data_dir / MANIFEST_FILE, self.data_dir / DATASET_FILE
        if not manifest.is_file() or not dataset.is_file():
            raise ValueError(f"data_dir {str(self.data_dir)!r} holds no finished dataset store "
                             f"({MANIFEST_FILE} and {DATASET_FILE}); run phm-generate first")
        self.manifest = read_json(manifest)
        self.file = h5py.File(dataset, "r")
        self.metadata = json.loads(self.file.attrs["metadata"])
        if verify:
            for name, info in self.manifest["splits"].items():
                digests = split_digests(self.file[name])
                if digests != info["sha256"]:
                    bad = sorted(k for k in digests if digests[k] != info["sha256"].get(k))
                    raise ValueError(f"{dataset}: split {name} arrays {bad} do not match {MANIFEST_FILE}")

    @property
    def splits(self) -> list[str]:
        return list(self.manifest["splits"])

    def split(self, name: str) -> SplitView:
        if name not in self.manifest["splits"]:
            raise ValueError(f"split {name!r} is not in the store {str(self.data_dir)!r}; splits: {self.splits}")
        return SplitView(self.file[name])

    @property
    def time(self) -> np.ndarray:
        return self.file["time"][()]

    @property
    def command(self) -> np.ndarray:
        return self.file["command"][()]

    def close(self) -> None:
        self.file.close()

    def __enter__(self) -> Self:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def split_digests(group: h5py.Group, rows_per_read: int = 1024) -> dict[str, str]:
    """SHA-256 of each array of a split (C-order bytes), read ``rows_per_read`` rows at a time."""
    out = {}
    for name in ARRAYS:
        ds = group[name]
        h = hashlib.sha256()
        for start in range(0, ds.shape[0], rows_per_read):
            h.update(np.ascontiguousarray(ds[start:start + rows_per_read]).tobytes())
        out[name] = h.hexdigest()
    return out
