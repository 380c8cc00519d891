"""Small synthetic data for the surrogate tests: low-rank "currents" with a known map k -> signal, and a
writer of dataset stores in the layout of ``phm_torch.data.store`` (what phm-generate writes)."""

from __future__ import annotations

import json
import math
from pathlib import Path

import h5py
import numpy as np
import torch

from phm_torch.data.store import ARRAYS, DATASET_FILE, MANIFEST_FILE, split_digests, write_json

N_E = 801  # samples per synthetic record (the real records have 10001)
RATE = 20000.0  # [Hz]
N_LATENT = 10  # rank of the synthetic signal family


def basis(n_e: int = N_E, rank: int = N_LATENT) -> torch.Tensor:
    """(n_e, rank) smooth, localized shapes (chirp-like bursts), float64, orthonormalized."""
    t = torch.linspace(0.0, 1.0, n_e, dtype=torch.float64)
    cols = [
        torch.sin(2 * math.pi * (i + 1) * t * (1 + t)) * torch.exp(-(((t - (i + 0.5) / rank) / 0.25) ** 2))
        for i in range(rank)
    ]
    q, _ = torch.linalg.qr(torch.stack(cols, 1))
    return q


def features(k: torch.Tensor) -> torch.Tensor:
    """(B, N_LATENT) latent amplitudes: an invertible, mildly nonlinear function of k (B, 8)."""
    f = torch.cat([k, (k[:, :1] * k[:, 1:2]), torch.sin(2.0 * k[:, 2:3])], 1)
    return f * torch.linspace(30.0, 3.0, N_LATENT, dtype=k.dtype)


def signals(k: torch.Tensor, noise: float = 0.0, seed: int = 0) -> torch.Tensor:
    """(B, N_E) float32 records y = y0 + V f(k) (+ white noise of std ``noise`` [A])."""
    k64 = k.to(torch.float64)
    t = torch.linspace(0.0, 1.0, N_E, dtype=torch.float64)
    y0 = 5.0 + 2.0 * torch.sin(2 * math.pi * 3 * t)
    y = y0 + features(k64) @ basis().T
    if noise:
        y = y + noise * torch.randn(y.shape, generator=torch.Generator().manual_seed(seed), dtype=torch.float64)
    return y.float()


def faults(n: int, seed: int) -> torch.Tensor:
    """(n, 8) fault vectors uniform in [0, 1] (float64)."""
    return torch.rand(n, 8, generator=torch.Generator().manual_seed(seed), dtype=torch.float64)


def health(k: torch.Tensor) -> torch.Tensor:
    """(n,) bool labels with a curved (cubic) boundary: healthy when the damage is small."""
    score = 1.0 - (k[:, 0] ** 2 + 0.8 * k[:, 1] + 0.5 * k[:, 2] * k[:, 3] + 0.6 * k[:, 7] ** 3)
    return score > 0.25


def write_store(
    data_dir: Path,
    sizes: dict[str, int],
    seed: int = 0,
    noise: float = 0.0,
    drop: dict[str, str] | None = None,
    n_time: int = N_E,
) -> Path:
    """Write a finished store with the given splits. For bad stores: ``drop`` = {split: array} leaves
    that array out; ``n_time`` != N_E gives a time grid inconsistent with the records. Returns data_dir."""
    data_dir = Path(data_dir)
    data_dir.mkdir(parents=True, exist_ok=True)
    splits = {}
    with h5py.File(data_dir / DATASET_FILE, "w") as f:
        f.attrs["metadata"] = json.dumps({"source": "tests/surrogate_data.py"})
        f.create_dataset("time", data=np.arange(n_time) / RATE)
        f.create_dataset("command", data=np.zeros(n_time))
        for i, (name, n) in enumerate(sizes.items()):
            k = faults(n, seed + 17 * i)
            y = signals(k, noise, seed + i).numpy()
            arrays = {
                "K": k.numpy(),
                "current": y,
                "position": np.zeros_like(y),
                "healthy": health(k).numpy().astype(np.uint8),
                "margins": np.zeros((n, 5)),
            }
            g = f.create_group(name)
            for a in ARRAYS:
                if (drop or {}).get(name) != a:
                    g.create_dataset(a, data=arrays[a])
            splits[name] = {
                "count": n,
                "healthy": int(arrays["healthy"].sum()),
                "sha256": split_digests(g) if not drop else {},
            }
    write_json(
        data_dir / MANIFEST_FILE,
        {
            "format": 1,
            "fingerprint": f"test-{seed}",
            "splits": splits,
            "arrays": list(ARRAYS),
            "signal_samples": n_time,
        },
    )
    return data_dir
