"""Report figures computed from a trained bundle and the validation split (the paper's offline studies)."""

from __future__ import annotations

import time
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import torch

from ..plotting import save_figure
from ..surrogates.fdi_mlp import FDIMLP
from ..surrogates.gappy_pod import GappyPOD
from ..surrogates.metrics import err_alpha, err_k
from ..surrogates.trainlm import TrainLM


def err_alpha_vs_modes(bundle, current: torch.Tensor, path: Path, max_modes: int | None = None) -> dict:
    """Gappy-POD coefficient error (median and IQR over signals) against retained modes, the bundle's points."""
    pod = bundle.pod
    limit = min(max_modes or pod.n_modes, bundle.gappy.n_points, pod.modes_.shape[1])
    # from 2 modes: err_alpha divides by the range of the coefficients over the modes, zero for one mode
    counts = sorted({m for m in (2, 3, 5, 8, 10, 12, 15, 18, 22, 26, 30) if m <= limit} | {limit})
    x = current.to(pod.modes_.dtype)
    rows = []
    for m in counts:
        modes, mean = pod.modes_[:, :m], pod.mean_
        full = (x - mean) @ modes
        gappy = GappyPOD(modes, mean, bundle.indices)
        alpha, _ = gappy(gappy.select(x))
        e = err_alpha(alpha, full)
        q = torch.quantile(e.double(), torch.tensor([0.25, 0.5, 0.75], dtype=torch.float64))
        rows.append(
            {
                "n_modes": m,
                "median": float(q[1]),
                "q25": float(q[0]),
                "q75": float(q[2]),
                "energy": float(pod.cumulative_energy()[m - 1]) if hasattr(pod, "cumulative_energy") else None,
            }
        )
    fig, ax = plt.subplots(figsize=(7, 4))
    ax.errorbar(
        [r["n_modes"] for r in rows],
        [100 * r["median"] for r in rows],
        yerr=[[100 * (r["median"] - r["q25"]) for r in rows], [100 * (r["q75"] - r["median"]) for r in rows]],
        fmt="x",
        capsize=3,
        label="ours: median, IQR band",
    )
    ax.axhline(2.0, color="r", ls="--", lw=1, label="paper: < 2 % at 22 modes")
    ax.set_xlabel("retained POD modes n_m")
    ax.set_ylabel("err_alpha [%]")
    ax.set_yscale("log")
    ax.grid(alpha=0.3)
    ax.legend()
    save_figure(fig, path)
    return {"rows": rows, "figure": str(path)}


def placement(bundle, sample_rate: float, path: Path) -> Path:
    """Selected sample times over the first POD mode (paper Fig. 'placement of 30 sampling points')."""
    mode = bundle.pod.modes_[:, 0].double()
    t = torch.arange(mode.numel(), dtype=torch.float64) / sample_rate
    idx = bundle.indices
    fig, ax = plt.subplots(figsize=(9, 3.5))
    ax.plot(t, mode, lw=0.8, label="first POD mode")
    ax.plot(t[idx], mode[idx], "o", ms=5, label=f"{idx.numel()} selected samples")
    ax.set_xlabel("time [s]")
    ax.grid(alpha=0.3)
    ax.legend()
    save_figure(fig, path)
    return path


def hidden_neuron_study(
    bundle,
    train_current: torch.Tensor,
    train_k: torch.Tensor,
    val_current: torch.Tensor,
    val_k: torch.Tensor,
    sizes: list[int],
    epochs: int,
    path: Path,
    seed: int = 0,
) -> list[dict]:
    """err_k and train/evaluation time against hidden neurons (LM-trained MLPs on gappy coefficients)."""
    gappy = bundle.gappy
    dtype = gappy.modes_hat.dtype
    a_tr, _ = gappy(gappy.select(train_current.to(dtype)))
    a_va, _ = gappy(gappy.select(val_current.to(dtype)))
    rows = []
    for h in sizes:
        torch.manual_seed(seed)
        net = FDIMLP(a_tr.shape[1], h).to(dtype).set_normalization(a_tr)
        t0 = time.perf_counter()
        TrainLM(net, forward_name="preactivation").fit(a_tr, train_k.to(dtype), epochs=epochs)
        t_train = time.perf_counter() - t0
        with torch.no_grad():
            one = a_va[:1]
            t0 = time.perf_counter()
            for _ in range(200):
                net(one)
            t_eval = (time.perf_counter() - t0) / 200
            rows.append(
                {"n_hidden": h, "err_k": err_k(net(a_va), val_k.to(dtype)), "train_s": t_train, "eval_us": 1e6 * t_eval}
            )
    fig, axes = plt.subplots(3, 1, figsize=(7, 8), sharex=True)
    hs = [r["n_hidden"] for r in rows]
    axes[0].plot(hs, [100 * r["err_k"] for r in rows], "o-", label="ours")
    axes[0].axhline(5.0, color="r", ls="--", lw=1, label="paper: ~5 % at 20 neurons")
    axes[0].set_ylabel("err_k [%]")
    axes[0].legend()
    axes[1].plot(hs, [r["eval_us"] for r in rows], "o-")
    axes[1].set_ylabel("evaluation [us]")
    axes[2].plot(hs, [r["train_s"] for r in rows], "o-")
    axes[2].set_ylabel("training [s]")
    axes[2].set_xlabel("hidden neurons")
    for ax in axes:
        ax.grid(alpha=0.3)
    save_figure(fig, path)
    return rows


def fdi_per_parameter(mae: list[float], path: Path) -> Path:
    """Mean |k_i error| per fault parameter against the paper's ~1 %."""
    names = [f"k{i + 1}" for i in range(len(mae))]
    fig, ax = plt.subplots(figsize=(7, 3.5))
    ax.bar(names, [100 * v for v in mae])
    ax.axhline(1.0, color="r", ls="--", lw=1, label="paper: at most ~1 %")
    ax.set_ylabel("mean |k_i error| [%]")
    ax.legend()
    ax.grid(alpha=0.3, axis="y")
    save_figure(fig, path)
    return path
