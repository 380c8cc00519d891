"""Figures of the RUL evaluation (the paper's RUL-vs-expected plots and three-panel error comparison)."""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import torch

from ..plotting import save_figure


def rul_vs_expected(reference: torch.Tensor, estimates: dict[str, torch.Tensor], path: Path) -> Path:
    """Estimated RUL (median with 5-95 % bars) against the reference median, reference band shaded."""
    order = torch.argsort(reference[:, 1])
    x = reference[order, 1].numpy()
    fig, axes = plt.subplots(1, len(estimates), figsize=(6 * len(estimates), 5), squeeze=False)
    for ax, (label, est) in zip(axes[0], estimates.items()):
        e = est[order].numpy()
        low = (e[:, 1] - e[:, 0]).clip(min=0)  # a band may be degenerate (or NaN when untrustworthy)
        high = (e[:, 2] - e[:, 1]).clip(min=0)
        ax.fill_between(
            x,
            reference[order, 0].numpy(),
            reference[order, 2].numpy(),
            color="0.85",
            label="reference 5-95 % (physics model)",
        )
        ax.errorbar(
            x, e[:, 1], yerr=[low, high], fmt="x", color="C0", ms=4, elinewidth=0.6, label=f"{label}: median and 5-95 %"
        )
        top = max(float(x.max(initial=1.0)), 1.0)
        ax.plot([0, top], [0, top], "r--", lw=1, label="ideal")
        ax.set_xlabel("expected RUL (reference median) [h]")
        ax.set_ylabel("estimated RUL [h]")
        ax.set_title(label)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
    save_figure(fig, path)
    return path


def error_panels(reference: torch.Tensor, true_k: torch.Tensor, full_flow: torch.Tensor, path: Path) -> Path:
    """Three panels: physics-model uncertainty, error from the true k, error of the full flow [h]."""
    usable = reference[:, 1] > 0
    ref = reference[usable]
    x = ref[:, 1].numpy()
    panels = [
        ("physics model: q95 - q5 (Delta_RUL x RUL)", (ref[:, 2] - ref[:, 0]).numpy()),
        ("RUL step (true k): |q50 - ref|", (true_k[usable, 1] - ref[:, 1]).abs().numpy()),
        ("full online flow: |q50 - ref|", (full_flow[usable, 1] - ref[:, 1]).abs().numpy()),
    ]
    fig, axes = plt.subplots(1, 3, figsize=(15, 4.5), sharey=True)
    for ax, (title, y) in zip(axes, panels):
        ax.scatter(x, y, s=10)
        ax.set_title(title)
        ax.set_xlabel("expected RUL [h]")
        ax.grid(alpha=0.3)
    axes[0].set_ylabel("[h]")
    save_figure(fig, path)
    return path
