"""Plots of actuator signals (matplotlib, Agg backend: no display needed).

:func:`plot_signals` overlays several runs (simulated cases, or a measurement and its simulation) on
shared time axes: one panel with the command and the position, one with the current, one with the
tracking error, and one per further channel requested.
"""

from __future__ import annotations

import os
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np

_LABELS = {
    "position": "position [mrad]",
    "current": "current [A]",
    "tracking_error": "tracking error [mrad]",
    "speed": "motor speed [rad/s]",
    "motor_angle": "motor angle [rad]",
    "user_angle": "user angle [mrad]",
    "ia": "i_a [A]",
    "ib": "i_b [A]",
    "ic": "i_c [A]",
}
_SCALE = {"command": 1e3, "position": 1e3, "tracking_error": 1e3, "user_angle": 1e3}


def save_figure(fig: Any, path: str | os.PathLike, dpi: int = 110) -> Path:
    """Lay out, write (PNG at ``dpi``, creating the folder) and close a figure; returns the path."""
    fig.tight_layout()
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=dpi)
    plt.close(fig)
    return path


def _np(value: Any) -> np.ndarray:
    if hasattr(value, "detach"):
        value = value.detach().cpu().numpy()
    return np.asarray(value, dtype=np.float64).reshape(-1)


def plot_signals(
    time: Any,
    channels_by_run: Mapping[str, Mapping[str, Any]],
    path: str | os.PathLike,
    extra_channels: Sequence[str] = (),
    tracking_error: bool = True,
    title: str | None = None,
    styles: Mapping[str, Mapping[str, Any]] | None = None,
) -> Path:
    """Overlay several runs into one PNG.

    Args:
        time: the common time axis (n,) [s], or a mapping {run label: time (n_run,)} when runs are sampled
            differently (e.g. a measurement and a simulation).
        channels_by_run: {run label: {channel: (n,) array or tensor}}; channels used: ``command``,
            ``position`` [rad], ``current`` [A] and any in ``extra_channels``. Missing channels are skipped
            for that run.
        path: the PNG file (parent directories are created).
        extra_channels: further channels to plot, one panel each (e.g. ``("speed", "ia")``).
        tracking_error: add a panel with command - position [mrad] for runs that have both.
        title: figure title.
        styles: optional {run label: matplotlib line kwargs} (colour, linestyle...).

    Returns:
        The path written.
    """
    if not channels_by_run:
        raise ValueError("plot_signals: no runs to plot")
    panels = ["position", "current"]
    if tracking_error:
        panels.append("tracking_error")
    panels += [c for c in extra_channels if c not in panels]
    fig, axes = plt.subplots(len(panels), 1, sharex=True, figsize=(10, 2.4 * len(panels) + 0.6), squeeze=False)
    axes = axes[:, 0]
    styles = styles or {}
    command_drawn: list[np.ndarray] = []
    for i, (label, chans) in enumerate(channels_by_run.items()):
        t = _np(time[label] if isinstance(time, Mapping) else time)
        style = {"color": f"C{i}", "linewidth": 1.0, **styles.get(label, {})}
        data = {name: _np(v) for name, v in chans.items()}
        for name, v in data.items():
            if v.shape != t.shape:
                raise ValueError(
                    f"plot_signals: run {label!r} channel {name!r} has {v.size} samples, its time axis {t.size}"
                )
        if "command" in data and "position" in data:
            data["tracking_error"] = data["command"] - data["position"]
        for ax, panel in zip(axes, panels, strict=True):
            if panel in data:
                ax.plot(t, data[panel] * _SCALE.get(panel, 1.0), label=label, **style)
        # draw each distinct command once, in black, behind the positions
        if "command" in data and not any(
            c.shape == data["command"].shape and np.allclose(c, data["command"]) for c in command_drawn
        ):
            cmd_label = "command" if not command_drawn else f"command ({label})"
            axes[0].plot(t, data["command"] * 1e3, color="k", linestyle="--", linewidth=0.8, label=cmd_label, zorder=0)
            command_drawn.append(data["command"])
    for ax, panel in zip(axes, panels, strict=True):
        ax.set_ylabel(_LABELS.get(panel, panel))
        ax.grid(True, alpha=0.3)
    axes[0].legend(loc="upper left", fontsize="small", ncol=min(4, len(channels_by_run) + 1))
    axes[-1].set_xlabel("time [s]")
    if title:
        fig.suptitle(title)
    return save_figure(fig, path)
