"""Training data for the surrogates, read from a dataset store (``phm_torch.data.DatasetStore``).

The POD needs the whole snapshot matrix in memory (10,000 x 10,001 float32 = 400 MB at paper scale), so
each split is read once, in row blocks, into plain tensors; everything downstream works on those.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch

from ..data.store import DatasetStore
from ..drive_range import peak_current
from ..faults import N_FAULTS

READ_ROWS = 512  # rows per HDF5 read


@dataclass
class SplitData:
    """One split in memory.

    Attributes:
        name: split name.  k: (n, 8) float32 fault vectors.  current: (n, n_e) float32 envelope current [A].
        healthy: (n,) bool assessment-function labels (True = healthy).
    """

    name: str
    k: torch.Tensor
    current: torch.Tensor
    healthy: torch.Tensor

    def __len__(self) -> int:
        return int(self.k.shape[0])

    def rows(self, keep: torch.Tensor) -> SplitData:
        """The split restricted to the rows where ``keep`` (n,) bool is True."""
        return SplitData(self.name, self.k[keep], self.current[keep], self.healthy[keep])

    def peak_current(self) -> torch.Tensor:
        """(n,) the largest |envelope current| of each record [A] (NaN samples ignored)."""
        return peak_current(self.current)


def read_split(store: DatasetStore, name: str, n_samples: int, limit: int | None = None) -> SplitData:
    """Read split ``name`` (its first ``limit`` rows if given) and check its shapes and values."""
    try:
        view = store.split(name)
    except KeyError as e:
        raise ValueError(f"store {str(store.data_dir)!r}, split {name!r} lacks an array: {e}") from None
    n = len(view)
    if limit is not None:
        n = min(n, limit)
    where = f"store {str(store.data_dir)!r}, split {name!r}"
    if n == 0:
        raise ValueError(f"{where} is empty")
    shapes = {
        "K": (view.K.shape, (len(view), N_FAULTS)),
        "current": (view.current.shape, (len(view), n_samples)),
        "healthy": (view.healthy.shape, (len(view),)),
    }
    for arr, (got, want) in shapes.items():
        if tuple(got) != want:
            raise ValueError(
                f"{where}: {arr} has shape {tuple(got)}, expected {want} "
                f"(n rows, {n_samples} samples = the store's time grid)"
            )
    k = torch.from_numpy(np.asarray(view.K[:n], dtype=np.float32))
    if not torch.isfinite(k).all() or bool(((k < 0) | (k > 1)).any()):
        raise ValueError(f"{where}: K holds values outside [0, 1] or non-finite")
    current = torch.empty(n, n_samples, dtype=torch.float32)
    for start in range(0, n, READ_ROWS):
        stop = min(start + READ_ROWS, n)
        block = current[start:stop]
        block.copy_(torch.from_numpy(np.asarray(view.current[start:stop], dtype=np.float32)))
        # checked block by block: isfinite on the whole array would need ~2x its size in temporaries
        finite = torch.isfinite(block).all(1)
        if not finite.all():
            raise ValueError(f"{where}: current row {start + int(torch.nonzero(~finite)[0, 0])} holds NaN or inf")
    healthy = torch.from_numpy(np.asarray(view.healthy[:n]).astype(bool))
    return SplitData(name, k, current, healthy)


def load_store(
    data_dir: str | os.PathLike, splits: dict[str, str], limits: dict[str, int | None] | None = None
) -> tuple[dict[str, SplitData], torch.Tensor, dict[str, Any]]:
    """Read the requested splits of the store in ``data_dir``.

    Args:
        splits: role -> split name, e.g. ``{"train": "train", "val": "val"}``.
        limits: role -> largest number of rows to read (None = all).

    Returns:
        {role: SplitData}, the time grid (n_e,) [s] float64, and {"manifest", "metadata"} of the store
        with "nominal", the current (n_e,) [A] of its ``nominal`` split (None when it has none).
    """
    with DatasetStore(data_dir) as store:
        time = torch.from_numpy(np.asarray(store.time, dtype=np.float64))
        if time.ndim != 1 or time.numel() < 2:
            raise ValueError(f"store {str(data_dir)!r}: time has shape {tuple(time.shape)}, expected (n_e,)")
        out = {
            role: read_split(store, name, int(time.numel()), (limits or {}).get(role)) for role, name in splits.items()
        }
        info = {
            "manifest": store.manifest,
            "metadata": store.metadata,
            "nominal": (
                read_split(store, "nominal", int(time.numel())).current[0]
                if "nominal" in store.manifest.get("splits", {})
                else None
            ),
        }
    return out, time, info
