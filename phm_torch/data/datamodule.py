"""LightningDataModule over a dataset store: lazy HDF5 reads, deterministic batches, normalisations.

Normalisations (statistics from the ``train`` split only, computed in float64 by chunked reads):

* signal centring ``y_center``: ``nominal`` (subtract the nominal actuator's signal, the ``nominal``
  split: POD of the deviations from nominal), ``mean`` (subtract the training mean: classic POD
  snapshot centring) or ``none``;
* signal scaling ``y_scale``: ``std`` (divide by the RMS of the centred training signals, one scalar,
  so that POD energies are unchanged in proportion) or ``none``;
* fault-vector scaling ``k_scaling``: ``none`` (k already in [0, 1]), ``minmax`` (per parameter to
  [0, 1] over the training split) or ``standard`` (zero mean, unit variance per parameter).

A batch is a dict: ``k`` (B, 8) float32 scaled, ``y`` (B, n_e) float32 normalised signals, ``healthy``
(B,) float32 (1 = healthy), ``index`` (B,) int64 row in the split.
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import h5py
import lightning as L
import numpy as np
import torch
from torch.utils.data import DataLoader, Dataset

from .store import DATASET_FILE, DatasetStore

Y_CENTERS = ("nominal", "mean", "none")
Y_SCALES = ("std", "none")
K_SCALINGS = ("none", "minmax", "standard")
CHANNELS = ("current", "position")


class SplitDataset(Dataset):
    """Rows of one split, read lazily (the HDF5 file is opened in each worker process on first use).

    Args:
        path: ``dataset.h5``.  split: group name.  channel: ``current`` or ``position``.
        y_center (n_e,), y_scale (scalar), k_offset (8,), k_scale (8,): the normalisation
            y' = (y - y_center) / y_scale, k' = (k - k_offset) / k_scale.
    """

    def __init__(
        self,
        path: Path,
        split: str,
        channel: str,
        y_center: np.ndarray,
        y_scale: float,
        k_offset: np.ndarray,
        k_scale: np.ndarray,
    ):
        self.path, self.split, self.channel = Path(path), split, channel
        self.y_center = torch.as_tensor(y_center, dtype=torch.float32)
        self.y_scale = float(y_scale)
        self.k_offset = torch.as_tensor(k_offset, dtype=torch.float32)
        self.k_scale = torch.as_tensor(k_scale, dtype=torch.float32)
        with h5py.File(self.path, "r") as f:
            self.n = int(f[split]["K"].shape[0])
        self._file: h5py.File | None = None
        self._pid = -1

    def __len__(self) -> int:
        return self.n

    def _group(self) -> h5py.Group:
        if self._file is None or self._pid != os.getpid():  # one handle per worker process
            self._file = h5py.File(self.path, "r")
            self._pid = os.getpid()
        return self._file[self.split]

    def __getitems__(self, indices: Sequence[int]) -> list[dict[str, torch.Tensor]]:
        """A whole batch in one read per array (h5py wants increasing indices: sort, read, unsort)."""
        idx = np.asarray(indices, dtype=np.int64)
        order = np.argsort(idx, kind="stable")
        uniq, inverse = np.unique(idx[order], return_inverse=True)
        g = self._group()
        y = torch.from_numpy(g[self.channel][uniq][inverse])
        k = torch.from_numpy(g["K"][uniq][inverse]).to(torch.float32)
        h = torch.from_numpy(g["healthy"][uniq][inverse]).to(torch.float32)
        y = (y - self.y_center) / self.y_scale
        k = (k - self.k_offset) / self.k_scale
        out: list[dict[str, torch.Tensor]] = [{}] * len(idx)
        for pos, j in enumerate(order):
            out[j] = {"k": k[pos], "y": y[pos], "healthy": h[pos], "index": torch.tensor(int(idx[j]))}
        return out

    def __getitem__(self, i: int) -> dict[str, torch.Tensor]:
        return self.__getitems__([int(i)])[0]

    def __getstate__(self) -> dict[str, Any]:  # DataLoader workers: never send an open handle
        state = dict(self.__dict__)
        state["_file"], state["_pid"] = None, -1
        return state


def train_statistics(store: DatasetStore, channel: str, rows_per_read: int = 512) -> dict[str, np.ndarray]:
    """Mean signal (n_e,), per-parameter K min/max/mean/std (8,) of the train split, float64."""
    tr = store.split("train")
    ys, ks = getattr(tr, channel), tr.K[()].astype(np.float64)
    total = np.zeros(ys.shape[1])
    for start in range(0, ys.shape[0], rows_per_read):
        total += ys[start : start + rows_per_read].astype(np.float64).sum(0)
    return {
        "y_mean": total / ys.shape[0],
        "k_min": ks.min(0),
        "k_max": ks.max(0),
        "k_mean": ks.mean(0),
        "k_std": ks.std(0),
    }


def centred_rms(store: DatasetStore, channel: str, center: np.ndarray, rows_per_read: int = 512) -> float:
    """RMS of (train signal - center) over every sample of the train split."""
    ys = getattr(store.split("train"), channel)
    acc = 0.0
    for start in range(0, ys.shape[0], rows_per_read):
        acc += float(((ys[start : start + rows_per_read].astype(np.float64) - center) ** 2).sum())
    return float(np.sqrt(acc / (ys.shape[0] * ys.shape[1])))


class EMADataModule(L.LightningDataModule):
    """Train/val loaders over a store made by ``phm-generate``.

    Args:
        data_dir: the store directory.
        batch_size: rows per batch.
        channel: signal, ``current`` (the paper's) or ``position``.
        y_center, y_scale, k_scaling: normalisations (module docstring).
        seed: seeds the training shuffle (the same seed gives the same batches every epoch sequence).
        num_workers: DataLoader worker processes.
        train_split, val_split: split names.
    """

    def __init__(
        self,
        data_dir: str | os.PathLike,
        batch_size: int,
        channel: str = "current",
        y_center: str = "nominal",
        y_scale: str = "none",
        k_scaling: str = "none",
        seed: int = 0,
        num_workers: int = 0,
        train_split: str = "train",
        val_split: str = "val",
    ):
        super().__init__()
        for name, value, allowed in (
            ("channel", channel, CHANNELS),
            ("y_center", y_center, Y_CENTERS),
            ("y_scale", y_scale, Y_SCALES),
            ("k_scaling", k_scaling, K_SCALINGS),
        ):
            if value not in allowed:
                raise ValueError(f"data.{name} must be one of {list(allowed)}, got {value!r}")
        if isinstance(batch_size, bool) or not isinstance(batch_size, int) or batch_size < 1:
            raise ValueError(f"data.batch_size must be an integer >= 1, got {batch_size!r}")
        self.data_dir = Path(data_dir)
        self.batch_size, self.channel, self.seed, self.num_workers = batch_size, channel, int(seed), num_workers
        self.y_center_mode, self.y_scale_mode, self.k_scaling = y_center, y_scale, k_scaling
        self.train_split, self.val_split = train_split, val_split
        self.normalisation: dict[str, Any] | None = None
        self.train_set: SplitDataset | None = None
        self.val_set: SplitDataset | None = None

    def setup(self, stage: str | None = None) -> None:
        if self.normalisation is not None:
            return
        with DatasetStore(self.data_dir) as store:
            for split in (self.train_split, self.val_split):
                if self.channel not in store.split(split).group:  # store.split: a clear error when missing
                    raise ValueError(
                        f"split {split!r} holds no {self.channel!r} signals (the labels split holds "
                        "labels only); data.train_split / data.val_split must name signal splits"
                    )
            stats = train_statistics(store, self.channel)
            n_e = stats["y_mean"].shape[0]
            if self.y_center_mode == "nominal":
                center = getattr(store.split("nominal"), self.channel)[0].astype(np.float64)
            elif self.y_center_mode == "mean":
                center = stats["y_mean"]
            else:
                center = np.zeros(n_e)
            scale = centred_rms(store, self.channel, center) if self.y_scale_mode == "std" else 1.0
        if self.k_scaling == "minmax":
            k_off, k_scale = stats["k_min"], stats["k_max"] - stats["k_min"]
        elif self.k_scaling == "standard":
            k_off, k_scale = stats["k_mean"], stats["k_std"]
        else:
            k_off, k_scale = np.zeros(8), np.ones(8)
        k_scale = np.where(k_scale > 0, k_scale, 1.0)
        self.normalisation = {
            "y_center": center,
            "y_scale": float(scale if scale > 0 else 1.0),
            "k_offset": k_off,
            "k_scale": k_scale,
        }
        path = self.data_dir / DATASET_FILE
        args = (self.channel, center, self.normalisation["y_scale"], k_off, k_scale)
        self.train_set = SplitDataset(path, self.train_split, *args)
        self.val_set = SplitDataset(path, self.val_split, *args)

    def unscale_k(self, k: torch.Tensor) -> torch.Tensor:
        """Fault vectors (B, 8) back from the scaled space to [0, 1]."""
        if self.normalisation is None:
            raise ValueError("EMADataModule.unscale_k: call setup() first")
        n = self.normalisation
        return k * torch.as_tensor(n["k_scale"], dtype=k.dtype) + torch.as_tensor(n["k_offset"], dtype=k.dtype)

    def train_dataloader(self) -> DataLoader:
        self.setup()
        gen = torch.Generator().manual_seed(self.seed)
        return DataLoader(
            self.train_set,
            batch_size=self.batch_size,
            shuffle=True,
            generator=gen,
            num_workers=self.num_workers,
            persistent_workers=self.num_workers > 0,
        )

    def val_dataloader(self) -> DataLoader:
        self.setup()
        return DataLoader(
            self.val_set,
            batch_size=self.batch_size,
            shuffle=False,
            num_workers=self.num_workers,
            persistent_workers=self.num_workers > 0,
        )
