"""Figures of two or more actuators side by side, from their phm-run output directories (same scale), with
each figure's ratio to the first actuator's and whether it is within the allowed factor.

Each ``--run name=dir`` is a ``phm-run`` out_dir (``data/manifest.json``, ``train/metrics.json``,
``evaluate/metrics.json``); optional ``--lf name=report.json`` (a ``phm-fit-lf`` report: held-out HF-LF
current NRMSE) and ``--workbench name=bench.json`` (``scripts/bench_workbench.py``: hit rate) add those.
Figures where smaller is better (errors, missed faults) must be at most ``factor`` times the first's;
figures where larger is better (accuracies, coverage, hit rate) at least the first's divided by ``factor``;
the healthy fraction must lie in [0.15, 0.40].

    python scripts/compare_actuators.py --run reference=/tmp/ref_paper/run --run rudder=/tmp/rud_paper/run \
        --lf reference=ref_lf.report.json --lf rudder=rud_lf.report.json \
        --workbench reference=results/bench_ref.json --workbench rudder=results/bench_rud.json --out cmp.json

``--classifier-heldout name=report.json`` (``scripts/classifier_heldout.py``) takes that actuator's classifier accuracy
and missed-fault rate from thousands of independent labels instead of the val split's few hundred faulty vectors.

``--bootstrap N`` (e.g. 1000) adds each figure's 95 % interval and each ratio's, resampling every run's evaluation
splits (``phm_torch/report/figure_uncertainty.py``; every proportion, the held-out labels' and the workbench's cases
included, from its counts' Jeffreys posterior), and
calls each ratio ``within``, ``outside`` or ``undecided`` (its interval straddles the factor). It holds the
evaluation's sampling error alone, not a second training's.

``--figures name=cmp.json`` takes that actuator's figures from an earlier comparison: all of them when it has no
``--run`` (its run directory gone), else only those its run does not give (the LF fit, the workbench); actuators
named by ``--figures`` come first (the base is the first name).

Beside the figures, each run evaluated with phm-evaluate's crossing counts gets a line (and a ``crossings`` entry in
the JSON): how many of its reference crossings are jumps of phi_a's margin score and the RUL error from the true k on
each kind, so that a gap in that figure can be told apart as the assessment's or the classifier's.
"""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path
from typing import Any

import numpy as np

from phm_torch.io.atomic import atomic_open
from phm_torch.report.figure_uncertainty import interval, proportion_draws, ratio_status, run_figure_draws

HEALTHY_RANGE = (0.15, 0.40)
# figure -> (where: train | evaluate | lf | workbench | manifest, key, smaller is better)
FIGURES: dict[str, tuple[str, str, bool]] = {
    "hf_lf_current_nrmse_median": ("lf", "importance", True),
    "healthy_fraction_train": ("manifest", "train", False),
    "err_alpha_median": ("train", "err_alpha_median", True),
    "err_k": ("train", "err_k", True),
    "classifier_accuracy": ("train", "classifier_accuracy", False),
    "classifier_missed_fault_rate": ("train", "missed_fault_rate", True),
    "verdict_accuracy": ("train", "chain_accuracy", False),
    "verdict_missed_fault_rate": ("train", "chain_missed_fault_rate", True),
    "rul_err_median_true_k": ("evaluate", "rul_err_median_true_k", True),
    "rul_band_coverage_true_k": ("evaluate", "rul_band_coverage_true_k", False),
    "rul_err_median_full_flow": ("evaluate", "rul_err_median_full_flow", True),
    "rul_band_coverage_full_flow": ("evaluate", "rul_band_coverage_full_flow", False),
    "workbench_hit_rate": ("workbench", "hit_rate", False),
}


def _pairs(items: list[str] | None, flag: str) -> dict[str, Path]:
    out: dict[str, Path] = {}
    for item in items or []:
        name, sep, path = item.partition("=")
        if not sep or not name or not path:
            raise SystemExit(f"compare_actuators: error: {flag} must be name=path, got {item!r}")
        out[name] = Path(path)
    return out


def _read(path: Path) -> dict[str, Any]:
    if not path.is_file():
        raise SystemExit(f"compare_actuators: error: no such file {str(path)!r}")
    return json.loads(path.read_text())


def _lf_median(report: dict[str, Any]) -> float | None:
    """Held-out importance-sampled median current NRMSE of the LF model the fit kept."""
    kept = "fitted" if report.get("kept") == "fitted" else "physical"
    try:
        return float(report["nrmse"]["importance"][kept]["current"]["median"])
    except (KeyError, TypeError):
        return None


HELDOUT = {"classifier_accuracy": "accuracy", "classifier_missed_fault_rate": "missed_fault_rate"}


def figures(run: Path, lf: Path | None, bench: Path | None, heldout: Path | None = None) -> dict[str, float | None]:
    """Every figure of one actuator (None where its source is missing); the classifier's from ``heldout`` if given."""
    sources = {"train": _read(run / "train" / "metrics.json"), "evaluate": _read(run / "evaluate" / "metrics.json")}
    manifest = _read(run / "data" / "manifest.json")
    out: dict[str, float | None] = {}
    for name, (where, key, _) in FIGURES.items():
        if where == "manifest":
            split = manifest["splits"][key]
            out[name] = split["healthy"] / split["count"] if split["count"] else None
        elif where == "lf":
            out[name] = _lf_median(_read(lf)) if lf else None
        elif where == "workbench":
            out[name] = float(_read(bench)["summary"][key]) if bench else None
        else:
            value = sources[where].get(key)
            out[name] = float(value) if isinstance(value, (int, float)) else None
    if heldout is not None:
        report = _read(heldout)
        out.update({name: float(report[key]) for name, key in HELDOUT.items()})
    out["actuator"] = sources["train"].get("actuator")  # type: ignore[assignment]
    return out


def figure_draws(run: Path, bench: Path | None, heldout: Path | None, draws: int, seed: int) -> dict[str, np.ndarray]:
    """Bootstrap draws of one actuator's figures (those its per-record files or counts give)."""
    out = run_figure_draws(run, draws, seed)
    if heldout is not None:
        report = _read(heldout)
        n, faulty = int(report["n"]), int(report["faulty"])
        out["classifier_accuracy"] = proportion_draws(round(report["accuracy"] * n), n, draws, seed + 1)
        out["classifier_missed_fault_rate"] = proportion_draws(int(report["missed"]), faulty, draws, seed + 2)
    if bench is not None:
        summary = _read(bench)["summary"]
        cases = int(summary["effects"])
        out["workbench_hit_rate"] = proportion_draws(round(summary["hit_rate"] * cases), cases, draws, seed + 3)
    return out


def with_intervals(
    verdicts: dict[str, dict[str, Any]], draws: dict[str, dict[str, np.ndarray]], base_name: str, factor: float
) -> None:
    """Add each ratio's interval and status (within / outside / undecided) where both actuators have draws."""
    base = draws.get(base_name, {})
    for name, rows in verdicts.items():
        for fig, row in rows.items():
            a, b = base.get(fig), draws.get(name, {}).get(fig)
            if a is not None and b is not None and fig != "healthy_fraction_train":
                row.update(ratio_status(a, b, FIGURES[fig][2], factor))


def status_tally(rows: dict[str, dict[str, Any]]) -> dict[str, int]:
    """How many of an actuator's ratios are within, outside or undecided (those with an interval)."""
    statuses = [row["status"] for row in rows.values() if "status" in row]
    return {status: statuses.count(status) for status in ("within", "outside", "undecided")}


def compare(table: dict[str, dict[str, Any]], factor: float) -> dict[str, dict[str, Any]]:
    """Per actuator after the first: per figure the ratio to the first's and whether it meets the target."""
    names = list(table)
    base = table[names[0]]
    verdicts: dict[str, dict[str, Any]] = {}
    for name in names[1:]:
        rows = {}
        for fig, (_, _, smaller) in FIGURES.items():
            a, b = base.get(fig), table[name].get(fig)
            if a is None or b is None:
                rows[fig] = {"ratio": None, "met": None}
                continue
            if fig == "healthy_fraction_train":
                rows[fig] = {"ratio": b / a if a else None, "met": HEALTHY_RANGE[0] <= b <= HEALTHY_RANGE[1]}
                continue
            ratio = b / a if a else (math.inf if b else 1.0)
            met = ratio <= factor if smaller else ratio >= 1.0 / factor
            rows[fig] = {"ratio": ratio, "met": bool(met)}
        verdicts[name] = rows
    return verdicts


def markdown(table: dict[str, dict[str, Any]], verdicts: dict[str, dict[str, Any]]) -> str:
    names = list(table)
    lines = ["| figure | " + " | ".join(names) + " | ratio | met |", "|---" * (len(names) + 3) + "|"]
    for fig in FIGURES:
        cells = ["-" if table[n].get(fig) is None else f"{table[n][fig]:.4g}" for n in names]
        last = verdicts.get(names[-1], {}).get(fig, {}) if len(names) > 1 else {}
        ratio = "-" if last.get("ratio") is None else f"{last['ratio']:.2f}"
        if "status" in last:
            ratio += f" [{last['ratio_lo']:.2f}, {last['ratio_hi']:.2f}]"
        met = {True: "yes", False: "**no**", None: "-"}[last.get("met")]
        if "status" in last:
            met += f" ({last['status']})"
        lines.append(f"| {fig} | " + " | ".join(cells) + f" | {ratio} | {met} |")
    return "\n".join(lines)


CROSSING_KEYS = (
    "rul_reference_crossings",
    "rul_reference_jump_crossings",
    "rul_err_median_true_k_smooth",
    "rul_err_median_true_k_jump",
)


def crossings(run: Path) -> dict[str, float | int] | None:
    """How a run's reference crossings happen (phm-evaluate's counts, prognostics/crossings.py): a RUL error from
    the true k that sits on jumps of phi_a's margin score is the assessment's, not the classifier's. None for a run
    evaluated before the counts existed."""
    metrics = _read(run / "evaluate" / "metrics.json")
    if not all(k in metrics for k in CROSSING_KEYS):
        return None
    return {k: metrics[k] for k in CROSSING_KEYS}


def crossings_line(name: str, c: dict[str, float | int]) -> str:
    pct = {k: f"{100 * c[k]:.2f} %" if c[k] == c[k] else "-" for k in CROSSING_KEYS[2:]}  # nan: no such crossing
    return (
        f"{name}: {c['rul_reference_jump_crossings']} of {c['rul_reference_crossings']} reference crossings jump; "
        f"RUL from the true k {pct['rul_err_median_true_k_smooth']} on the smooth ones, "
        f"{pct['rul_err_median_true_k_jump']} on the jumps"
    )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--run", action="append", required=True, help="name=phm-run out_dir (the first is the base)")
    ap.add_argument("--lf", action="append", help="name=phm-fit-lf report JSON")
    ap.add_argument("--workbench", action="append", help="name=bench_workbench JSON")
    ap.add_argument("--figures", action="append", help="name=earlier comparison JSON (its figures of that actuator)")
    ap.add_argument("--classifier-heldout", action="append", help="name=classifier_heldout.py report JSON")
    ap.add_argument("--factor", type=float, default=1.3, help="allowed factor against the first actuator")
    ap.add_argument("--bootstrap", type=int, default=0, help="draws for 95 %% intervals (0: none; e.g. 1000)")
    ap.add_argument("--out", type=Path, default=None, help="JSON written (atomically)")
    args = ap.parse_args()
    if not args.factor >= 1.0:
        raise SystemExit(f"compare_actuators: error: --factor must be >= 1, got {args.factor}")
    runs, lfs, benches = _pairs(args.run, "--run"), _pairs(args.lf, "--lf"), _pairs(args.workbench, "--workbench")
    heldouts = _pairs(args.classifier_heldout, "--classifier-heldout")
    if set(heldouts) - set(runs):
        raise SystemExit(
            f"compare_actuators: error: --classifier-heldout needs a --run of {sorted(set(heldouts) - set(runs))}"
        )
    earlier = {}
    for name, path in _pairs(args.figures, "--figures").items():
        recorded = _read(path).get("figures", {})
        if name not in recorded:
            raise SystemExit(f"compare_actuators: error: --figures {name}={path}: it holds no figures of {name!r}")
        earlier[name] = recorded[name]
    table = {}
    for name in dict.fromkeys([*earlier, *runs]):
        own = figures(runs[name], lfs.get(name), benches.get(name), heldouts.get(name)) if name in runs else {}
        table[name] = {**earlier.get(name, {}), **{k: v for k, v in own.items() if v is not None}}
    verdicts = compare(table, args.factor)
    intervals: dict[str, dict[str, list[float]]] = {}
    if args.bootstrap:
        if args.bootstrap < 100:
            raise SystemExit(f"compare_actuators: error: --bootstrap must be 0 or >= 100, got {args.bootstrap}")
        draws = {
            name: figure_draws(runs[name], benches.get(name), heldouts.get(name), args.bootstrap, 10 * i)
            for i, name in enumerate(table)
            if name in runs
        }
        if names_without := [n for n in table if n not in runs]:
            print(f"no intervals for {names_without}: their figures come from --figures, not a run")
        with_intervals(verdicts, draws, next(iter(table)), args.factor)
        intervals = {n: {f: list(interval(v)) for f, v in d.items()} for n, d in draws.items()}
    print(markdown(table, verdicts))
    tally = {name: status_tally(rows) for name, rows in verdicts.items()}
    for name, counts in tally.items():
        if sum(counts.values()):
            print(f"{name}: " + ", ".join(f"{n} {status}" for status, n in counts.items()) + " (95 % intervals)")
    reads = {name: c for name, path in runs.items() if (c := crossings(path)) is not None}
    for name, c in reads.items():
        print(crossings_line(name, c))
    if args.out:
        with atomic_open(args.out, "w") as fh:
            json.dump(
                {
                    "factor": args.factor,
                    "figures": table,
                    "verdicts": verdicts,
                    "intervals": intervals,
                    "status_tally": tally,
                    "bootstrap": args.bootstrap,
                    "runs": {k: str(v) for k, v in runs.items()},
                    "figures_from": {k: str(v) for k, v in _pairs(args.figures, "--figures").items()},
                    "classifier_from": {k: str(v) for k, v in heldouts.items()},
                    "crossings": reads,
                },
                fh,
                indent=2,
            )


if __name__ == "__main__":
    main()
