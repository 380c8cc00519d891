"""Aggregate a ``phm-train`` sweep (Hydra multirun directory) into the seed paper's figures and tables.

Reads every ``<sweep>/<job>/metrics.json`` (and ``predictions.pt``, loaded with ``weights_only=True``)
and writes into ``<sweep>/aggregate/`` (or ``--out``):

* ``err_alpha_vs_modes.png``: gappy-POD coefficient error vs retained modes, median and IQR band
  (paper: "Offline preliminary assessment of Gappy POD coefficients identification");
* ``fdi_vs_hidden.png``: err_k, training time and evaluation time per signal vs hidden neurons
  (paper: "Error in fault identification ... for variable number of neurons");
* ``placement.png``: the selected samples over the first POD mode, one panel per run that differs
  in the selector or the number of points (paper: "Placement of 30 sampling points over the first mode");
* ``fdi_error_per_parameter.png``: |k_est - k_act| per fault parameter, box plots (paper: "FDI error
  on each fault parameter"), for the run named by ``--run`` (default: the lowest err_k);
* ``summary.json`` and ``summary.md``: one row per run (the swept values and the main metrics), the
  selector comparison (coefficient error, condition number, err_k clean / noisy / missing) and the
  classifier confusion table of the chosen run (paper Table "Performance of the SVM").

A figure whose swept variable took fewer than two values in the sweep is skipped (and says so).

Usage: python scripts/aggregate_sweep.py multirun/train/<date>/<time> [--out DIR] [--run JOB]
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import torch

from phm_torch.faults import FAULT_NAMES
from phm_torch.io.atomic import atomic_open

COLUMNS = (
    "n_modes",
    "n_points",
    "n_hidden",
    "selector",
    "model",
    "err_alpha_median",
    "err_alpha_iqr",
    "gappy_condition_number",
    "err_k",
    "err_k_noise",
    "err_k_missing",
    "classifier_accuracy",
    "missed_fault_rate",
    "false_alarm_rate",
    "fdi_latency_us_p50",
)


def load_runs(sweep: Path) -> list[dict[str, Any]]:
    runs = []
    for path in sorted(sweep.glob("*/metrics.json"), key=lambda p: (len(p.parent.name), p.parent.name)):
        m = json.loads(path.read_text())
        m["job"] = path.parent.name
        m["dir"] = path.parent
        runs.append(m)
    if not runs:
        raise SystemExit(f"aggregate_sweep: no */metrics.json under {sweep}")
    return runs


def varying(runs: list[dict[str, Any]], key: str) -> bool:
    return len({json.dumps(r.get(key)) for r in runs}) > 1


def fig_modes(runs: list[dict[str, Any]], out: Path) -> str:
    if not varying(runs, "n_modes"):
        return "skipped: n_modes does not vary"
    rs = sorted(runs, key=lambda r: r["n_modes"])
    x = [r["n_modes"] for r in rs]
    med = [100 * r["err_alpha_median"] for r in rs]
    lo, hi = [100 * r["err_alpha_q1"] for r in rs], [100 * r["err_alpha_q3"] for r in rs]
    fig, ax = plt.subplots(figsize=(6, 4))
    ax.fill_between(x, lo, hi, alpha=0.3, label="interquartile range")
    ax.plot(x, med, "x-", label="median")
    ax.set(
        xlabel="retained POD modes $n_m$",
        ylabel="$err_\\alpha$ [%]",
        yscale="log",
        title=f"Gappy POD coefficient error ({rs[0]['n_points']} points)",
    )
    ax.legend()
    fig.tight_layout()
    fig.savefig(out / "err_alpha_vs_modes.png", dpi=120)
    plt.close(fig)
    return "err_alpha_vs_modes.png"


def fig_hidden(runs: list[dict[str, Any]], out: Path) -> str:
    if not varying(runs, "n_hidden"):
        return "skipped: n_hidden does not vary"
    rs = sorted(runs, key=lambda r: r["n_hidden"])
    x = [r["n_hidden"] for r in rs]
    fig, axes = plt.subplots(3, 1, figsize=(6, 7), sharex=True)
    axes[0].plot(x, [100 * r["err_k"] for r in rs], "o-")
    axes[0].set_ylabel("$err_k$ [%]")
    axes[1].plot(x, [r["timing"]["fdi_eval_per_signal_us"] for r in rs], "o-", label="batched")
    axes[1].plot(x, [r["fdi_latency_us_p50"] for r in rs], "s--", label="single signal (gappy + MLP)")
    axes[1].set_ylabel("evaluation [us]")
    axes[1].legend()
    axes[2].plot(x, [r["timing"]["fdi_train_s"] for r in rs], "o-")
    axes[2].set(ylabel="training [s]", xlabel="hidden neurons $n_h$")
    fig.suptitle("FDI network vs hidden neurons")
    fig.tight_layout()
    fig.savefig(out / "fdi_vs_hidden.png", dpi=120)
    plt.close(fig)
    return "fdi_vs_hidden.png"


def fig_placement(runs: list[dict[str, Any]], out: Path) -> str:
    keyed = {}
    for r in runs:
        keyed.setdefault((r["selector"], r["n_points"]), r)
    sel = list(keyed.values())[:6]
    fig, axes = plt.subplots(len(sel), 1, figsize=(7, 1.8 * len(sel) + 0.6), sharex=True, squeeze=False)
    for ax, r in zip(axes[:, 0], sel):
        a = torch.load(r["dir"] / "predictions.pt", weights_only=True)
        t, v1, idx = a["time"], a["mode_1"], a["indices"]
        ax.plot(t, v1, lw=0.7)
        ax.plot(t[idx], v1[idx], "o", ms=4)
        ax.set_ylabel("$v_1$")
        ax.set_title(f"{r['selector']}: {r['n_points']} points", fontsize=9)
    axes[-1, 0].set_xlabel("t [s]")
    fig.tight_layout()
    fig.savefig(out / "placement.png", dpi=120)
    plt.close(fig)
    return "placement.png"


def fig_per_parameter(run: dict[str, Any], out: Path) -> str:
    a = torch.load(run["dir"] / "predictions.pt", weights_only=True)
    err = (a["k_hat"] - a["k"]).abs() * 100
    fig, ax = plt.subplots(figsize=(7, 4))
    ax.boxplot([err[:, i].numpy() for i in range(8)], showfliers=False)
    ax.plot(range(1, 9), err.mean(0).numpy(), "x", label="mean")
    ax.set_xticks(range(1, 9), [f"k{i + 1}\n{n}" for i, n in enumerate(FAULT_NAMES)], fontsize=7)
    ax.set(ylabel="|k_est - k_act| [%]", title=f"FDI error per fault parameter (run {run['job']})")
    ax.legend()
    fig.tight_layout()
    fig.savefig(out / "fdi_error_per_parameter.png", dpi=120)
    plt.close(fig)
    return "fdi_error_per_parameter.png"


def fmt(v: Any) -> str:
    if isinstance(v, float):
        return f"{v:.4g}"
    return "-" if v is None else str(v)


def markdown(runs: list[dict[str, Any]], chosen: dict[str, Any]) -> str:
    lines = ["| job | " + " | ".join(COLUMNS) + " |", "|---" * (len(COLUMNS) + 1) + "|"]
    lines += ["| " + r["job"] + " | " + " | ".join(fmt(r.get(c)) for c in COLUMNS) + " |" for r in runs]
    c = chosen["classifier_confusion"]
    lines += [
        "",
        f"Classifier confusion, run {chosen['job']} ({c['n_healthy']} healthy, {c['n_faulty']} faulty):",
        "",
        "| | count | rate |",
        "|---|---|---|",
        f"| healthy recognised | {c['healthy_correct']} | {c['healthy_correct'] / max(c['n_healthy'], 1):.4f} |",
        f"| faulty recognised | {c['faulty_correct']} | {c['faulty_correct'] / max(c['n_faulty'], 1):.4f} |",
        f"| missed faults (faulty -> healthy) | {c['missed_faults']} | {c['missed_fault_rate']:.4f} |",
        f"| false alarms (healthy -> faulty) | {c['false_alarms']} | {c['false_alarm_rate']:.4f} |",
        f"| total correct | {c['healthy_correct'] + c['faulty_correct']} | {c['accuracy']:.4f} |",
    ]
    return "\n".join(lines) + "\n"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("sweep", type=Path, help="Hydra multirun directory of phm-train")
    ap.add_argument("--out", type=Path, default=None, help="output directory (default: <sweep>/aggregate)")
    ap.add_argument("--run", default=None, help="job for the per-parameter figure and confusion table")
    args = ap.parse_args()
    runs = load_runs(args.sweep)
    out = args.out or args.sweep / "aggregate"
    out.mkdir(parents=True, exist_ok=True)
    chosen = next((r for r in runs if r["job"] == args.run), None) if args.run else min(runs, key=lambda r: r["err_k"])
    if chosen is None:
        raise SystemExit(f"aggregate_sweep: no job {args.run!r} in {args.sweep}")
    figures = {
        "err_alpha_vs_modes": fig_modes(runs, out),
        "fdi_vs_hidden": fig_hidden(runs, out),
        "placement": fig_placement(runs, out),
        "fdi_error_per_parameter": fig_per_parameter(chosen, out),
    }
    rows = [
        {"job": r["job"], **{c: r.get(c) for c in COLUMNS}, "fdi_mae": r.get("fdi_mae"), "timing": r.get("timing")}
        for r in runs
    ]
    summary = {
        "sweep": str(args.sweep),
        "figures": figures,
        "runs": rows,
        "chosen_run": chosen["job"],
        "classifier_confusion": chosen["classifier_confusion"],
    }
    with atomic_open(out / "summary.json", "w") as fh:
        json.dump(summary, fh, indent=2)
        fh.write("\n")
    with atomic_open(out / "summary.md", "w") as fh:
        fh.write(markdown(runs, chosen))
    print(json.dumps(figures, indent=2))
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
