"""Figures of the workbench report (matplotlib, Agg). Each function returns the PNG as bytes."""

from __future__ import annotations

import io
import math
from collections.abc import Mapping, Sequence
from typing import Any

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np

SCALE = {
    "position": (1e3, "mrad"),
    "user_angle": (1e3, "mrad"),
    "current": (1.0, "A"),
    "speed": (1.0, "rad/s"),
    "motor_angle": (1.0, "rad"),
    "ia": (1.0, "A"),
    "ib": (1.0, "A"),
    "ic": (1.0, "A"),
}
MAPS = (
    ("speed", "motor speed |ω| [rad/s]"),
    ("reversal", "time from reversal [ms]"),
    ("mechanical_angle", "θ_m (wrapped to ±π) [rad]"),
    ("electrical_angle", "θ_e mod 2π [rad]"),
    ("current", "|current| [A]"),
)


def _png(fig: Any) -> bytes:
    buf = io.BytesIO()
    fig.tight_layout()
    fig.savefig(buf, format="png", dpi=90)
    plt.close(fig)
    return buf.getvalue()


def overlay(
    time: np.ndarray,
    measured: Mapping[str, np.ndarray],
    models: Mapping[str, Mapping[str, np.ndarray]],
    sigma: Mapping[str, float],
    windows: Sequence[Mapping[str, float]],
    title: str,
) -> bytes:
    """Measured vs simulated channels of one record, and the errors of each model with the +-2 sigma band;
    the worst windows shaded."""
    chans = list(measured)
    fig, axes = plt.subplots(2 * len(chans), 1, sharex=True, figsize=(11, 2.3 * 2 * len(chans) + 0.5), squeeze=False)
    axes = axes[:, 0]
    for k, c in enumerate(chans):
        f, unit = SCALE.get(c, (1.0, ""))
        ax, ax_e = axes[2 * k], axes[2 * k + 1]
        ax.plot(time, measured[c] * f, color="0.55", lw=0.6, label="measured")
        for i, (label, sim) in enumerate(models.items()):
            ax.plot(time, sim[c] * f, color=f"C{i}", lw=0.9, label=label)
            ax_e.plot(time, (sim[c] - measured[c]) * f, color=f"C{i}", lw=0.5, label=label)
        band = 2 * sigma[c] * f
        ax_e.axhspan(-band, band, color="k", alpha=0.12, label="±2σ noise")
        ax.set_ylabel(f"{c} [{unit}]")
        ax_e.set_ylabel(f"error [{unit}]")
        for w in windows:
            for a in (ax, ax_e):
                a.axvspan(w["t_start"], w["t_end"], color="red", alpha=0.08)
        for a in (ax, ax_e):
            a.grid(True, alpha=0.3)
    axes[0].legend(loc="upper left", fontsize="small", ncol=4)
    axes[1].legend(loc="upper left", fontsize="small", ncol=4)
    axes[-1].set_xlabel("time [s]  (red: worst windows of the model)")
    fig.suptitle(title)
    return _png(fig)


def maps(profiles: Mapping[str, Mapping[str, dict]], channels: Sequence[str]) -> bytes:
    """Residual maps (normalised residual r / sigma) of each model in physical coordinates, one row per channel."""
    fig, axes = plt.subplots(len(channels), len(MAPS), figsize=(3.3 * len(MAPS), 2.6 * len(channels)), squeeze=False)
    for i, (label, prof) in enumerate(profiles.items()):
        for row, c in enumerate(channels):
            for col, (name, xlabel) in enumerate(MAPS):
                ax = axes[row, col]
                x = np.asarray(prof[name]["x"]) * (1e3 if name == "reversal" else 1.0)
                data = prof[name][c]
                if "mean" in data:
                    ax.plot(x, data["mean"], color=f"C{i}", lw=1.0, label=label)
                else:
                    for j, (branch, d) in enumerate(data.items()):
                        ax.plot(x, d["mean"], color=f"C{i}", lw=1.0, ls=("-", "--")[j % 2], label=f"{label} ({branch})")
                ax.axhline(0, color="k", lw=0.5)
                ax.grid(True, alpha=0.3)
                if row == len(channels) - 1:
                    ax.set_xlabel(xlabel)
                if col == 0:
                    ax.set_ylabel(f"{c}: mean r/σ")
    axes[0, 0].legend(fontsize="x-small")
    axes[0, 1].legend(fontsize="x-small")
    fig.suptitle("Where the model fails: residual maps (solid: ω > 0 / + to −, dashed: ω < 0 / − to +)")
    return _png(fig)


def harmonic_bars(
    harmonics: Mapping[str, Mapping[str, np.ndarray]], channels: Sequence[str], pole_pairs: int, slots: int
) -> bytes:
    """Harmonic content of the normalised residual vs mechanical order of the rotor angle."""
    fig, axes = plt.subplots(len(channels), 1, figsize=(10, 2.4 * len(channels)), squeeze=False)
    n = len(harmonics)
    for i, (label, h) in enumerate(harmonics.items()):
        for row, c in enumerate(channels):
            ax = axes[row, 0]
            orders = np.arange(1, len(h[c]) + 1)
            ax.bar(orders + (i - (n - 1) / 2) * 0.8 / n, h[c], width=0.8 / n, color=f"C{i}", label=label)
            ax.set_ylabel(f"{c}: amplitude r/σ")
    for row in range(len(channels)):
        ax = axes[row, 0]
        for k in range(1, 3):
            ax.axvline(k * slots, color="r", lw=0.6, ls=":")
        ax.grid(True, alpha=0.3)
    axes[0, 0].legend(fontsize="small")
    axes[-1, 0].set_xlabel(f"mechanical harmonic order (electrical = order / {pole_pairs}; red: slot harmonics)")
    return _png(fig)


def spectra(spec: Mapping[str, Mapping[str, np.ndarray]], sigma: Mapping[str, float], sample_rate: float) -> bytes:
    """Welch PSD of the error of each model, with the white-noise floor 2 sigma^2 / f_s."""
    chans = list(sigma)
    fig, axes = plt.subplots(1, len(chans), figsize=(5.5 * len(chans), 3.2), squeeze=False)
    for i, (label, s) in enumerate(spec.items()):
        for col, c in enumerate(chans):
            axes[0, col].semilogy(s["f"], s[c], color=f"C{i}", lw=0.9, label=label)
    for col, c in enumerate(chans):
        ax = axes[0, col]
        ax.axhline(2 * sigma[c] ** 2 / sample_rate, color="k", ls="--", lw=0.8, label="noise floor")
        ax.set_xscale("log")
        ax.set_xlabel("frequency [Hz]")
        ax.set_ylabel(f"{c} error PSD [unit²/Hz]")
        ax.grid(True, alpha=0.3, which="both")
    axes[0, 0].legend(fontsize="small")
    return _png(fig)


def correlations(
    white: Mapping[str, Mapping[str, dict]], cross: Mapping[str, Mapping[str, dict]], sample_rate: float
) -> bytes:
    """Residual autocorrelation and residual-command cross-correlation with their significance bands."""
    chans = list(next(iter(white.values())))
    fig, axes = plt.subplots(len(chans), 2, figsize=(11, 2.6 * len(chans)), squeeze=False)
    for i, label in enumerate(white):
        for row, c in enumerate(chans):
            w, x = white[label][c], cross[label][c]
            lags = np.arange(len(w["autocorrelation"])) / sample_rate * 1e3
            axes[row, 0].plot(
                lags[1:],
                w["autocorrelation"][1:],
                color=f"C{i}",
                lw=0.9,
                label=f"{label} (Ljung-Box p={w['p_value']:.2g})",
            )
            axes[row, 1].plot(
                np.asarray(x["lags"]) / sample_rate * 1e3,
                x["correlation"],
                color=f"C{i}",
                lw=0.9,
                label=f"{label} (p={x['p_value']:.2g})",
            )
            for col, band in ((0, w["band"]), (1, x["band"])):
                axes[row, col].axhspan(-band, band, color="k", alpha=0.1)
    for row, c in enumerate(chans):
        axes[row, 0].set_ylabel(f"{c}")
        for col in range(2):
            axes[row, col].grid(True, alpha=0.3)
            axes[row, col].legend(fontsize="x-small")
    axes[0, 0].set_title("whiteness: residual autocorrelation (band: 99 %)")
    axes[0, 1].set_title("residual vs command cross-correlation (band: 99 %)")
    axes[-1, 0].set_xlabel("lag [ms]")
    axes[-1, 1].set_xlabel("lag [ms]")
    return _png(fig)


def candidate_bars(rows: Sequence[Mapping[str, Any]], threshold_log10: float) -> bytes:
    """-log10 p of each candidate's score test, best first, with the Bonferroni threshold."""
    fig, ax = plt.subplots(figsize=(8, 0.45 * len(rows) + 1.3))
    names = [r["effect"] for r in rows][::-1]
    vals = [min(-(r["log10_p_value"] or 0.0), 1e4) for r in rows][::-1]
    colours = ["C3" if r["significant"] else "0.6" for r in rows][::-1]
    ax.barh(names, vals, color=colours)
    ax.axvline(-threshold_log10, color="k", ls="--", lw=0.8, label="significance (Bonferroni)")
    ax.set_xscale("symlog", linthresh=10)
    ax.set_xlabel("-log10 p (score test; red: significant)")
    ax.legend(fontsize="small")
    ax.grid(True, alpha=0.3, axis="x")
    return _png(fig)


def before_after(rows: Sequence[Mapping[str, Any]], floor: Mapping[str, float]) -> bytes:
    """NRMSE per channel of each model, with the noise floor."""
    chans = [c for c in floor if c != "total"] + ["total"]
    fig, ax = plt.subplots(figsize=(2.2 * len(chans) + 2, 3.2))
    n = len(rows)
    x = np.arange(len(chans))
    for i, r in enumerate(rows):
        ax.bar(
            x + (i - (n - 1) / 2) * 0.8 / n,
            [100 * r["nrmse"][c] for c in chans],
            width=0.8 / n,
            color=f"C{i}",
            label=r["model"],
        )
    for j, c in enumerate(chans):
        ax.hlines(
            100 * floor[c], j - 0.45, j + 0.45, color="k", ls="--", lw=1.0, label="noise floor" if j == 0 else None
        )
    ax.set_xticks(x, chans)
    ax.set_ylabel("NRMSE [%]")
    ax.legend(fontsize="small")
    ax.grid(True, alpha=0.3, axis="y")
    return _png(fig)


def attribution(shares: Mapping[str, float], title: str) -> bytes:
    """Input attribution of the neural closure."""
    fig, ax = plt.subplots(figsize=(7, 0.35 * len(shares) + 1.2))
    names = list(shares)[::-1]
    ax.barh(names, [100 * shares[n] for n in names], color="C2")
    ax.set_xlabel("share of the closure's input sensitivity [%]")
    ax.set_title(title)
    ax.grid(True, alpha=0.3, axis="x")
    return _png(fig)


def finite(x: float) -> float | None:
    """JSON-safe float: None for NaN/inf."""
    return float(x) if x is not None and math.isfinite(float(x)) else None
