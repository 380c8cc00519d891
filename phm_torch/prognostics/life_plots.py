"""Figures of a life track against its truth (issue 25): RUL vs hours with the alpha cone and both methods,
filtered k and k_hat vs the true k, and the fleet table (CSV + PNG).

Censored bounds (null in track.json) are drawn at the top of the RUL axis with an upward triangle.
"""

from __future__ import annotations

import csv
import math
import os
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np

from ..faults import FAULT_NAMES
from ..io.atomic import atomic_open
from ..plotting import save_figure
from ..tracking.measurement import READINGS
from .damage import PHASE_INDEX
from .life_metrics import METHODS, _quantiles, lambda_index

_STYLE = {"tracker": {"color": "C0", "label": "tracker"}, "snapshot": {"color": "C3", "label": "snapshot"}}


def select_actuators(truth: Mapping[str, Any], max_actuators: int) -> list[str]:
    """Up to ``max_actuators`` ids with an end of life, evenly spread over the wear-rate scale (slowest to
    fastest), so the figures show the fleet's range rather than its first few ids."""
    ids = [a for a, g in truth["actuators"].items() if g.get("eol_hours") is not None]
    ids.sort(key=lambda a: (truth["actuators"][a].get("rate_scale") or 1.0, a))
    if len(ids) <= max_actuators:
        return ids
    picks = np.unique(np.linspace(0, len(ids) - 1, max_actuators).round().astype(int))
    return [ids[i] for i in picks]


def whose(track: Mapping[str, Any]) -> str:
    """``actuator / command`` of a track.json (its pipeline's), for figure titles; '' where it records none."""
    names = [(track.get(key) or {}).get("name") for key in ("actuator", "command")]
    return " / ".join(str(n) for n in names if n)


def _titled(fig: Any, track: Mapping[str, Any]) -> Any:
    """Put the actuator and command on the figure: a figure saved alone still says whose life it shows."""
    title = whose(track)
    if title:
        fig.suptitle(title, fontsize=10)
    return fig


def _grid(n: int, width: float = 5.0, height: float = 3.6) -> tuple[Any, np.ndarray]:
    cols = min(3, n)
    rows = math.ceil(n / cols)
    fig, axes = plt.subplots(rows, cols, figsize=(width * cols, height * rows), squeeze=False)
    for ax in axes.flat[n:]:
        ax.set_visible(False)
    return fig, axes.flat


def _rul_panel(
    ax: Any,
    a: str,
    track_a: Mapping[str, Any],
    truth_a: Mapping[str, Any],
    alpha: float,
    lam: float,
    horizon_alpha: float,
) -> None:
    insp = track_a["inspections"]
    hours = np.array([float(i["hours"]) for i in insp])
    ood = np.array([bool(i.get("out_of_distribution", False)) for i in insp])
    eol = float(truth_a["eol_hours"])
    t0 = float(truth_a["inspections"][0]["hours"])
    life = eol - t0
    top = 1.6 * life  # censored bounds are drawn here
    h = np.linspace(t0, eol, 50)
    true = eol - h
    ax.fill_between(h, (1 - alpha) * true, (1 + alpha) * true, color="0.85", label=f"alpha cone (+-{alpha:.0%})")
    ax.plot(h, true + horizon_alpha * life, ":", color="0.4", lw=0.8)
    ax.plot(
        h,
        (true - horizon_alpha * life).clip(min=0),
        ":",
        color="0.4",
        lw=0.8,
        label=f"PH bounds (+-{horizon_alpha:.0%} of life)",
    )
    ax.plot(h, true, "k-", lw=1.2, label="true RUL")
    for method, (key, _) in METHODS.items():
        q = np.array([_quantiles(i, key) for i in insp]).reshape(-1, 3)
        censored = ~np.isfinite(q)
        qc = np.where(censored, top, q)
        st = _STYLE[method]
        ax.fill_between(hours[~ood], qc[~ood, 0], qc[~ood, 2], color=st["color"], alpha=0.18, step=None)
        ax.plot(hours[~ood], qc[~ood, 1], "o-", ms=2.5, lw=1.0, color=st["color"], label=f"{st['label']} p50, 5-95 %")
        cens = censored.any(axis=1) & ~ood
        if cens.any():
            ax.plot(hours[cens], np.full(cens.sum(), top), "^", ms=4, color=st["color"])
    if ood.any():
        ax.plot(hours[ood], np.zeros(ood.sum()), "x", color="0.3", label="out of distribution (not fused)")
    i = lambda_index(hours, t0, eol, lam)
    if i is not None:
        ax.axvline(hours[i], color="0.5", ls="--", lw=0.8)
    ax.axvline(eol, color="k", ls="-", lw=0.6)
    ax.set_ylim(0, top * 1.05)
    ax.set_xlim(t0, hours.max() + 1)
    scale = truth_a.get("rate_scale")
    ax.set_title(f"{a}: s = {scale:.2f}, EOL {eol:.0f} h" if scale is not None else f"{a}: EOL {eol:.0f} h", fontsize=9)
    ax.set_xlabel("hours [h]")
    ax.set_ylabel("RUL [h]")
    ax.grid(alpha=0.3)


def rul_figure(
    track: Mapping[str, Any],
    truth: Mapping[str, Any],
    ids: Sequence[str],
    path: Path,
    alpha: float = 0.2,
    lam: float = 0.5,
    horizon_alpha: float = 0.1,
) -> Path:
    """One panel per actuator: true RUL, the alpha cone, PH bounds, both methods' p50 and 5-95 % band."""
    fig, axes = _grid(len(ids))
    for ax, a in zip(axes, ids):
        _rul_panel(ax, a, track["actuators"][a], truth["actuators"][a], alpha, lam, horizon_alpha)
    axes[0].legend(fontsize=7, loc="upper right")
    return save_figure(_titled(fig, track), path)


def _named(values: Any, names: Sequence[str]) -> dict[str, float]:
    """A {name: v} dict, or a list in FAULT_NAMES order, as {name: v}."""
    if values is None:
        return {}
    if isinstance(values, Mapping):
        return dict(values)
    return dict(zip(names, values))


def _interval(insp: Sequence[Mapping[str, Any]], key: str, name: str, centre: np.ndarray) -> np.ndarray:
    """(2, n) distances below / above ``centre`` of the inspections' ``key`` interval of ``name``; NaN where
    there is none (a null interval, or a track without that key)."""
    lohi = np.array([((i.get(key) or {}).get(name) or [np.nan, np.nan]) for i in insp], float).reshape(-1, 2)
    return np.stack([centre - lohi[:, 0], lohi[:, 1] - centre]).clip(min=0)


def readings(insp: Sequence[Mapping[str, Any]], name: str) -> tuple[np.ndarray, np.ndarray]:
    """What the filter read of component ``name`` at each inspection (n,) and its interval as distances below /
    above (2, n): the first of :data:`~phm_torch.tracking.measurement.READINGS` the inspection has."""
    read = [next((r for r in READINGS if i.get(r[0]) is not None), READINGS[-1]) for i in insp]
    centre = np.array([_named(i.get(key), FAULT_NAMES).get(name, np.nan) for i, (key, _) in zip(insp, read)], float)
    bars = [_interval([i], bound, name, centre[n : n + 1]) for n, (i, (_, bound)) in enumerate(zip(insp, read))]
    return centre, np.concatenate(bars, axis=1) if bars else np.zeros((2, 0))


def damage_figure(track: Mapping[str, Any], truth: Mapping[str, Any], ids: Sequence[str], path: Path) -> Path:
    """One panel per actuator, each damage component that moves over the life (the phase k7 is never a
    damage) as its change since the truth's initial k0 (so a drift around 0.5 shares the axis with damages
    near 0): true (line), filtered (dashed, ``k_filtered_interval`` shaded), the reading the filter fused (dots:
    the near-nominal FDI's, or k_hat through the response's inverse, or k_hat; its interval as bars)."""
    fig, axes = _grid(len(ids))
    handles: dict[str, Any] = {}
    for ax, a in zip(axes, ids):
        g, insp = truth["actuators"][a], track["actuators"][a]["inspections"]
        gh = np.array([float(i["hours"]) for i in g["inspections"]])
        hours = np.array([float(i["hours"]) for i in insp])
        filtered = np.array(
            [[_named(i.get("k_filtered"), FAULT_NAMES).get(n, np.nan) for n in FAULT_NAMES] for i in insp], float
        ).reshape(len(insp), len(FAULT_NAMES))
        # a truth written by another tool may hold the end of life only: the filtered k then says what moves
        has_true = bool(g["inspections"]) and all("k_true" in i for i in g["inspections"])
        k_true = np.array([i["k_true"] for i in g["inspections"]], float).reshape(len(gh), -1) if has_true else None
        shown = k_true if k_true is not None else filtered
        start = np.nan_to_num(shown[0]) if len(shown) else np.zeros(len(FAULT_NAMES))
        k0 = np.asarray(g.get("k0") or start, float)
        spread = np.nanmax(shown, 0) - np.nanmin(shown, 0) if len(shown) else np.zeros(0)
        moving = [j for j in range(len(spread)) if j != PHASE_INDEX and spread[j] > 1e-9]
        for j in moving:
            name = FAULT_NAMES[j] if j < len(FAULT_NAMES) else f"k{j + 1}"
            color = f"C{j}"  # one colour per component in every panel
            if k_true is not None:
                (handles[name],) = ax.plot(gh, k_true[:, j] - k0[j], "-", color=color, lw=1.4)
            filt = filtered[:, j]
            khat, bars = readings(insp, name)
            (line,) = ax.plot(hours, filt - k0[j], "--", color=color, lw=1.0)
            handles.setdefault(name, line)
            ax.errorbar(hours, khat - k0[j], yerr=bars, fmt=".", color=color, ms=3, alpha=0.5, elinewidth=0.5)
            band = _interval(insp, "k_filtered_interval", name, filt)
            if np.isfinite(band).any():
                ax.fill_between(hours, filt - k0[j] - band[0], filt - k0[j] + band[1], color=color, alpha=0.15)
        eol = g.get("eol_hours")
        if eol is not None:
            ax.axvline(float(eol), color="k", lw=0.6)
        ax.set_title(f"{a}: true (line), filtered (dashed), reading (dots)", fontsize=9)
        ax.set_xlabel("hours [h]")
        ax.set_ylabel("k - k0 [-]")
        ax.grid(alpha=0.3)
    if handles:
        axes[0].legend(list(handles.values()), list(handles), fontsize=7, loc="upper left")
    return save_figure(_titled(fig, track), path)


def fleet_rows(track: Mapping[str, Any], truth: Mapping[str, Any] | None = None) -> list[dict[str, Any]]:
    """Each actuator's latest inspection sorted by RUL p5 (censored / null last), with the true RUL at
    that hour when the truth is given. Rows: actuator, hours, rul_p5/p50/p95 [h] (None = censored),
    rul_censored, healthy, p_faulty, rul_true [h]."""
    rows = []
    for a, t in track["actuators"].items():
        if not t["inspections"]:
            continue
        last = t["inspections"][-1]
        p5, p50, p95 = _quantiles(last, "rul_hours")
        row = {
            "actuator": a,
            "hours": float(last["hours"]),
            "rul_p5": p5,
            "rul_p50": p50,
            "rul_p95": p95,
            "rul_censored": bool(last.get("rul_censored", False)),
            "healthy": last.get("healthy"),
            "p_faulty": last.get("p_faulty"),
        }
        if truth is not None and a in truth["actuators"]:
            eol = truth["actuators"][a].get("eol_hours")
            row["rul_true"] = None if eol is None else float(eol) - row["hours"]
        rows.append(row)
    rows.sort(key=lambda r: (r["rul_p5"], r["actuator"]))
    for r in rows:
        for k in ("rul_p5", "rul_p50", "rul_p95"):
            r[k] = None if r[k] is None or math.isinf(r[k]) else r[k]
    return rows


def fleet_table(
    rows: Sequence[Mapping[str, Any]], csv_path: Path, png_path: Path, max_rows: int = 25, title: str = ""
) -> list[Path]:
    """The fleet list as CSV (every row) and as a PNG table (the first ``max_rows``: the most urgent; ``title``,
    e.g. the actuator and command, leads its heading)."""
    cols = ["actuator", "hours", "rul_p5", "rul_p50", "rul_p95", "rul_censored", "healthy", "p_faulty", "rul_true"]
    cols = [c for c in cols if any(c in r for r in rows)] or cols[:8]
    with atomic_open(csv_path, "w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=cols, extrasaction="ignore")
        w.writeheader()
        w.writerows(rows)

    def cell(v: Any) -> str:
        if v is None:
            return "censored"
        return (
            f"{v:.0f}"
            if isinstance(v, float) and not isinstance(v, bool) and abs(v) >= 10
            else (f"{v:.2f}" if isinstance(v, float) else str(v))
        )

    shown = rows[:max_rows]
    fig, ax = plt.subplots(figsize=(1.25 * len(cols), 0.32 * (len(shown) + 2) + 0.6))
    ax.axis("off")
    if shown:
        table = ax.table(cellText=[[cell(r.get(c)) for c in cols] for r in shown], colLabels=cols, loc="center")
        table.auto_set_font_size(False)
        table.set_fontsize(7)
    lead = f"{title}: " if title else ""
    ax.set_title(f"{lead}fleet, sorted by RUL p5 ({len(shown)} of {len(rows)} actuators)", fontsize=9)
    return [Path(csv_path), save_figure(fig, png_path)]


def plot_life(
    track: Mapping[str, Any],
    truth: Mapping[str, Any],
    out_dir: str | os.PathLike,
    max_actuators: int = 6,
    alpha: float = 0.2,
    lam: float = 0.5,
    horizon_alpha: float = 0.1,
) -> list[Path]:
    """Write life_rul.png, life_damage.png, life_fleet.csv and life_fleet.png under ``out_dir``.

    Args:
        track, truth: track.json and truth.json (issue 25's contract) as dicts.
        out_dir: folder (created).
        max_actuators: actuators drawn in the per-actuator figures (spread over the wear-rate scale).
        alpha, lam, horizon_alpha: the cone, the lambda inspection and the PH bounds (as evaluate_life).

    Returns:
        The paths written.
    """
    if not isinstance(max_actuators, int) or max_actuators < 1:
        raise ValueError(f"plot_life: max_actuators must be an int >= 1, got {max_actuators!r}")
    out = Path(out_dir)
    ids = [a for a in select_actuators(truth, max_actuators) if a in track.get("actuators", {})]
    paths: list[Path] = []
    if ids:
        paths.append(rul_figure(track, truth, ids, out / "life_rul.png", alpha, lam, horizon_alpha))
        paths.append(damage_figure(track, truth, ids, out / "life_damage.png"))
    paths += fleet_table(fleet_rows(track, truth), out / "life_fleet.csv", out / "life_fleet.png", title=whose(track))
    return paths
