"""The dataset store on disk: self-verifying chunk files, the merged HDF5 file, the manifest, and reads.

Layout of ``data_dir``::

    store.json             fingerprint + resolved generation config (written first; guards against mixing)
    chunks/chunk_00000.h5  rows [c * chunk_size, ...) of the global row list, one file per chunk
    chunks/labels_00000.h5 rows of the assessment-only ``labels`` split (if ``dataset.n_labels`` > 0)
    dataset.h5             the merged store: one group per split (see ``ARRAYS``), written last
    manifest.json          per split: count, healthy count, SHA-256 of every array (deterministic)

Every file is written under a temporary name and renamed into place (``io/atomic.py``), so a reader
never sees a half-written file. A chunk file carries the SHA-256 of its own arrays; ``read_chunk``
recomputes it, so a damaged chunk is detected and never used as data. Arrays, per split with n rows:

* ``K`` (n, 8) float64 fault vectors;  ``current`` (n, n_e) float32 HF filtered envelope current [A];
* ``position`` (n, n_e) float32 LVDT position [rad];  ``healthy`` (n,) uint8 phi_a (1 = healthy);
* ``margins`` (n, 5) float64, columns ``MARGIN_NAMES`` (Hz, deg, Hz, dB, Hz; nan = not measurable).

The optional split ``labels`` (``LABELS``: extra fault vectors labelled by phi_a, for the health
classifier) holds only ``LABEL_ARRAYS`` = K, healthy, margins (no signals); stores made before it
existed, or with ``dataset.n_labels`` = 0, lack it. ``read_labelled`` reads (K, healthy) of several splits.

The root of ``dataset.h5`` holds ``time`` (n_e,) [s] and ``command`` (n_e,) [rad], and the attribute
``metadata`` (JSON: resolved config, seeds, package version, git revision, fingerprint).
"""

from __future__ import annotations

import copy
import hashlib
import json
import os
from collections.abc import Iterator, Mapping, Sequence
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Self

import h5py
import numpy as np

from ..checks import build
from ..checks import device as torch_device
from ..io.atomic import atomic_open
from ..params import ActuatorParams
from ..provenance import from_config

ARRAYS = ("K", "current", "position", "healthy", "margins")
LABELS = "labels"  # the assessment-only split
LABEL_ARRAYS = ("K", "healthy", "margins")  # its arrays (no signals)
DATASET_FILE = "dataset.h5"
MANIFEST_FILE = "manifest.json"
STORE_FILE = "store.json"
CHUNK_DIR = "chunks"


class CorruptChunkError(ValueError):
    """A chunk file whose content does not match its checksum (or cannot be read)."""


@dataclass(frozen=True)
class ChunkLayout:
    """One kind of chunk file: its name prefix (``chunks/<prefix>_00000.h5``), its arrays, and the unit of
    its rows (progress bars, messages)."""

    prefix: str
    arrays: tuple[str, ...]
    unit: str


SIGNAL_CHUNKS = ChunkLayout("chunk", ARRAYS, "signal")  # rows of nominal|train|val|rul
LABEL_CHUNKS = ChunkLayout("labels", LABEL_ARRAYS, "label")  # rows of the labels split


def split_arrays(split: str) -> tuple[str, ...]:
    """The arrays of a split of ``dataset.h5``: ``LABEL_ARRAYS`` for ``labels``, ``ARRAYS`` otherwise."""
    return LABEL_ARRAYS if split == LABELS else ARRAYS


def array_digest(arrays: Mapping[str, np.ndarray], names: Sequence[str] = ARRAYS) -> str:
    """SHA-256 over the arrays ``names`` (name, dtype, shape, C-order bytes), in that order."""
    h = hashlib.sha256()
    for name in names:
        a = np.ascontiguousarray(arrays[name])
        h.update(f"{name}|{a.dtype.str}|{a.shape}|".encode())
        h.update(a.tobytes())
    return h.hexdigest()


@contextmanager
def atomic_h5(path: Path) -> Iterator[h5py.File]:
    """An HDF5 file written under a temporary name and renamed to ``path`` only if the block succeeds."""
    with atomic_open(path, "w+b") as fh, h5py.File(fh, "w", track_order=True) as f:
        yield f


def chunk_path(data_dir: Path, index: int, layout: ChunkLayout = SIGNAL_CHUNKS) -> Path:
    return Path(data_dir) / CHUNK_DIR / f"{layout.prefix}_{index:05d}.h5"


def write_chunk(
    path: Path, arrays: Mapping[str, np.ndarray], attrs: Mapping[str, Any], names: Sequence[str] = ARRAYS
) -> str:
    """Write the arrays ``names`` of one chunk atomically with their SHA-256; returns the digest."""
    digest = array_digest(arrays, names)
    with atomic_h5(path) as f:
        for name in names:
            f.create_dataset(name, data=arrays[name], track_times=False)
        for key, value in attrs.items():
            f.attrs[key] = value
        f.attrs["sha256"] = digest
    return digest


def read_chunk(path: Path, expect: Mapping[str, Any], names: Sequence[str] = ARRAYS) -> dict[str, np.ndarray]:
    """Read and verify the arrays ``names`` of a chunk: its checksum and the attributes in ``expect``
    (e.g. fingerprint, rows).

    Raises:
        CorruptChunkError: unreadable file, checksum mismatch or attribute mismatch.
    """
    try:
        with h5py.File(path, "r") as f:
            arrays = {name: f[name][()] for name in names}
            attrs = {k: f.attrs[k] for k in f.attrs}
    except (OSError, KeyError, ValueError) as e:
        raise CorruptChunkError(f"chunk {path}: unreadable ({e})") from None
    for key, value in expect.items():
        if key not in attrs or not np.array_equal(np.asarray(attrs[key]), np.asarray(value)):
            raise CorruptChunkError(f"chunk {path}: attribute {key} is {attrs.get(key)!r}, expected {value!r}")
    digest = array_digest(arrays, names)
    if attrs.get("sha256") != digest:
        raise CorruptChunkError(f"chunk {path}: checksum mismatch (stored {attrs.get('sha256')!r}, content {digest!r})")
    return arrays


def read_json(path: Path) -> Any:
    with open(path) as fh:
        return json.load(fh)


def write_json(path: Path, data: Any) -> None:
    with atomic_open(path, "w") as fh:
        json.dump(data, fh, indent=2, sort_keys=True)
        fh.write("\n")


class SplitView:
    """Lazy view of one split of an open ``dataset.h5`` (h5py datasets: slicing reads only those rows).

    Attributes: the split's arrays (``split_arrays``): K, current, position, healthy, margins; the
    ``labels`` split has no ``current`` / ``position``.
    """

    def __init__(self, group: h5py.Group):
        self.group = group
        self.name = group.name.strip("/")
        for name in split_arrays(self.name):
            setattr(self, name, group[name])

    def __getattr__(self, attr: str) -> Any:  # only called for a missing attribute
        if attr in ARRAYS:
            raise AttributeError(
                f"split {self.name!r} has no array {attr!r} (its arrays: "
                f"{list(split_arrays(self.name))}; the labels split holds no signals)"
            )
        raise AttributeError(attr)

    def __len__(self) -> int:
        return int(self.group["K"].shape[0])


def metadata_provenance(metadata: Mapping[str, Any]) -> dict[str, Any]:
    """``{"actuator", "command"}`` records of a store's ``metadata``; a store made before they were recorded
    gets them from the generation config it keeps."""
    recorded = metadata.get("provenance")
    if recorded is not None:
        return dict(recorded)
    return from_config(metadata.get("config") or {})


def recorded_actuator(metadata: Mapping[str, Any]) -> ActuatorParams | None:
    """The actuator a store's records were simulated for (the ``actuator`` node of the generation config its
    ``metadata`` keeps); ``None`` when the config records none (a store written by other tools)."""
    config = metadata.get("config") or {}
    if "actuator" not in config:
        return None
    try:
        return ActuatorParams.from_mapping(config["actuator"])
    except (ValueError, TypeError) as e:
        if str(e).startswith("actuator"):
            raise
        raise ValueError(f"actuator: {e}") from None


def recorded_assessment(
    metadata: Mapping[str, Any], device: str = "cpu", sweep: Mapping[str, Any] | None = None
) -> tuple[Any, ActuatorParams]:
    """The assessment function phi_a a store's labels were made with and its actuator, rebuilt from the
    generation config its ``metadata`` keeps, so that new labels are the store's own kind; ``sweep`` entries
    replace the recorded ``assessment.sweep``'s (another grid density, settling). Raises ``ValueError`` when
    the store records no actuator or assessment config."""
    config = metadata.get("config") or {}
    params = recorded_actuator(metadata)
    if params is None or "assessment" not in config:
        raise ValueError("the store does not record the actuator and assessment config its labels were made with")
    assessment = copy.deepcopy(dict(config["assessment"]))
    if sweep:
        assessment["sweep"] = {**(assessment.get("sweep") or {}), **sweep}
    return build(assessment, "assessment", params=params, device=torch_device(device)), params


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
            raise ValueError(
                f"data_dir {str(self.data_dir)!r} holds no finished dataset store "
                f"({MANIFEST_FILE} and {DATASET_FILE}); run phm-generate first"
            )
        self.manifest = read_json(manifest)
        self.file = h5py.File(dataset, "r")
        self.metadata = json.loads(self.file.attrs["metadata"])
        if verify:
            for name, info in self.manifest["splits"].items():
                digests = split_digests(self.file[name], split_arrays(name))
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
    def provenance(self) -> dict[str, Any]:
        """``{"actuator", "command"}`` records of the store (see :mod:`phm_torch.provenance`); a store made
        before they were recorded gets them from the generation config it keeps."""
        return metadata_provenance(self.metadata)

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


def split_digests(group: h5py.Group, names: Sequence[str] = ARRAYS, rows_per_read: int = 1024) -> dict[str, str]:
    """SHA-256 of each array ``names`` of a split (C-order bytes), read ``rows_per_read`` rows at a time."""
    out = {}
    for name in names:
        ds = group[name]
        h = hashlib.sha256()
        for start in range(0, ds.shape[0], rows_per_read):
            h.update(np.ascontiguousarray(ds[start : start + rows_per_read]).tobytes())
        out[name] = h.hexdigest()
    return out


def read_labelled(
    source: str | os.PathLike | h5py.File,
    splits: Sequence[str] = ("train", LABELS),
    optional: Sequence[str] = (LABELS,),
) -> tuple[np.ndarray, np.ndarray]:
    """Fault vectors and their phi_a labels from several splits of a store, concatenated in order.

    Args:
        source: a store directory, its ``dataset.h5``, or that file open in h5py.
        splits: the splits to read, e.g. ``("train", "labels")`` (the health classifier's training set).
        optional: those of ``splits`` that may be absent (``labels``: stores made with
            ``dataset.n_labels`` = 0 or before the split existed); absent ones are skipped.

    Returns:
        K (N, 8) float64 and healthy (N,) bool (True = healthy), N = the rows of the splits read.

    Raises:
        ValueError: no dataset file, a required split is missing, or a split's K / healthy is malformed.
    """
    if isinstance(source, h5py.File):
        return _read_labelled(source, splits, optional)
    path = Path(source)
    if path.is_dir():
        path = path / DATASET_FILE
    if not path.is_file():
        raise ValueError(f"{str(path)!r} is no dataset store file ({DATASET_FILE}); run phm-generate first")
    with h5py.File(path, "r") as f:
        return _read_labelled(f, splits, optional)


def _read_labelled(f: h5py.File, splits: Sequence[str], optional: Sequence[str]) -> tuple[np.ndarray, np.ndarray]:
    if isinstance(splits, str) or not splits:
        raise ValueError(f"read_labelled: splits must be a non-empty sequence of split names, got {splits!r}")
    present = [s for s in f if isinstance(f[s], h5py.Group)]
    missing = [s for s in splits if s not in present and s not in optional]
    if missing:
        raise ValueError(f"{f.filename}: the store lacks the split(s) {missing} (its splits: {present})")
    ks, hs = [], []
    for s in splits:
        if s not in present:
            continue
        g = f[s]
        if "K" not in g or "healthy" not in g:
            raise ValueError(f"{f.filename}: split {s!r} lacks K or healthy")
        k, h = np.asarray(g["K"][()], dtype=np.float64), np.asarray(g["healthy"][()])
        if k.ndim != 2 or k.shape[1] != 8 or h.shape != (k.shape[0],):
            raise ValueError(
                f"{f.filename}: split {s!r}: K has shape {k.shape}, healthy {h.shape}; expected (n, 8) and (n,)"
            )
        ks.append(k)
        hs.append(h.astype(bool))
    if not ks:
        return np.zeros((0, 8)), np.zeros(0, dtype=bool)
    return np.concatenate(ks), np.concatenate(hs)
