"""What the ``timing`` check (``phm_torch.online.timing_check``) does on val-like records of a pipeline's actuator, on
phm-predict's path: clean records (0-3 % noise) for its false rejections, and the current delayed or advanced by a
few milliseconds (a current-only record's trigger offset; with its command and position, the current channel
delayed alone) for what it catches; the 1 % records with their command and position on time ("clean_full"). Writes JSON: per case the right / wrong unflagged and flagged counts, the
timing check's share, and the ratio's distribution on the clean records for choosing its threshold.

    python scripts/timing_check_eval.py [--pipeline pretrained/online_surrogates_best.pt] [--vectors 500]
        [--out docs/trust/timing_check_pretrained.json]

The HF records are the corruption suite's clean ones (simulated once, cached under ``--cache``).
"""

from __future__ import annotations

import json
import time
from typing import Any

import numpy as np
import torch

from phm_torch.io.atomic import write_json
from phm_torch.online.corruption_suite import Case, clean_record_arguments, clean_records, contract_of, judgement
from phm_torch.online.corruptions import Record, delayed
from phm_torch.online.diagnosis import calibrated_interval, diagnose
from phm_torch.online.timing_check import TIMING_RATIO
from phm_torch.online.timing_tolerance import tolerance_seconds

DELAYS_MS = (0.5, 1.0, 2.0, 5.0, 10.0, -1.0, -3.0)  # the current moved by this (negative: it leads)
FULL_DELAYS_MS = (0.5, 2.0, 5.0)  # the same with the record's command and position on time
NOISE_INDEX = 2  # the clean records come at 0, 1, 2, 3 % noise, each twice: the first 1 % draw
THRESHOLDS = (1.5, 1.6, 1.7, 1.8, 2.0, 2.5, float("inf"))  # inf: without the check


def read(model: Any, contract: Any, case: Case, record: Record, tolerance: float) -> dict[str, Any]:
    """phm-predict's diagnosis of ``record`` (a current-only record's trigger ``tolerance`` [s]) judged against the
    case's truth, the timing check's values, whether any other check flagged it (so that other thresholds can be
    judged from the same run) and whether its verdict changed within the tolerance (said in its messages)."""
    out = diagnose(model, record, contract, timing_tolerance_s=tolerance)
    if out["out_of_distribution"]:
        lower, upper = calibrated_interval(model, out)
        out = {**out, "k_interval": {n: [a, b] for n, a, b in zip(out["k_hat"], lower.tolist(), upper.tolist())}}
    judged = judgement(out, case.k, case.healthy)
    timing = out["timing_check"] or {}
    bounds = [b for name, b in (out["k_interval"] or {}).items() if name != "eccentricity_phase"]
    return {
        "right": judged["right"],
        "flagged": judged["flagged"],
        "other_flag": bool([r for r in out["ood_reasons"] if r != "timing"]),
        "shift_s": timing.get("best_shift_s"),
        "ratio": timing.get("ratio"),
        "verdict_unstable": not (out["timing_tolerance"] or {}).get("verdict_stable", True),
        # the mean width of the damages' intervals (the tolerance's cost)
        "width": float(np.mean([b - a for a, b in bounds])) if bounds else None,
    }


def tally(rows: list[dict[str, Any]], threshold: float | None = None, min_shift_s: float = 3e-4) -> dict[str, Any]:
    """Right / wrong unflagged and flagged counts of ``rows``; with ``threshold``, the timing check's decision
    re-derived at it from the stored ratio and shift."""
    if threshold is None:
        flagged = [r["flagged"] for r in rows]
        timing = [r["flagged"] and not r["other_flag"] for r in rows]
    else:
        fires = [r["ratio"] is not None and abs(r["shift_s"]) >= min_shift_s and r["ratio"] >= threshold for r in rows]
        flagged = [r["other_flag"] or f for r, f in zip(rows, fires)]
        timing = [f and not r["other_flag"] for r, f in zip(rows, fires)]
    return {
        "cases": len(rows),
        "right_unflagged": sum(r["right"] and not f for r, f in zip(rows, flagged)),
        "wrong_unflagged": sum(not r["right"] and not f for r, f in zip(rows, flagged)),
        # of those, the verdict said to change within the trigger tolerance
        "wrong_unflagged_verdict_unstable": sum(
            not r["right"] and not f and r.get("verdict_unstable", False) for r, f in zip(rows, flagged)
        ),
        "flagged": sum(flagged),
        "flagged_by_timing_alone": sum(timing),
        "median_width_unflagged": _median([r.get("width") for r, f in zip(rows, flagged) if not f]),
    }


def _median(values: list[float | None]) -> float | None:
    kept = [v for v in values if v is not None]
    return float(np.median(kept)) if kept else None


def main(argv: list[str] | None = None) -> dict[str, Any]:
    parser = clean_record_arguments(__doc__.splitlines()[0], "timing_check.json")
    parser.add_argument(
        "--timing-tolerance", type=float, default=None, help="[s] phm-predict's timing_tolerance (default: its own)"
    )
    args = parser.parse_args(argv)
    tolerance = tolerance_seconds(args.timing_tolerance, "--timing-tolerance")
    if args.vectors < 1:
        raise ValueError(f"--vectors must be >= 1, got {args.vectors}")
    torch.set_num_threads(1)
    t0 = time.perf_counter()
    model = torch.jit.load(str(args.pipeline))
    contract = contract_of(model, args.pipeline)
    clean = clean_records(model, args.pipeline, args.vectors, args.cache)
    rate = float(model.n_full - 1) / float(clean[0].record.time[-1] - clean[0].record.time[0])
    report: dict[str, Any] = {
        "pipeline": str(args.pipeline),
        "threshold": contract.timing_ratio,
        "timing_tolerance_s": tolerance,
        "cases": {},
    }
    runs: dict[str, list[dict[str, Any]]] = {}
    runs["clean"] = [
        read(model, contract, c, Record(c.record.time, None, None, c.record.current), tolerance) for c in clean
    ]
    print(json.dumps({"clean": tally(runs["clean"]), "s": round(time.perf_counter() - t0)}), flush=True)
    cases = clean[NOISE_INDEX * args.vectors : (NOISE_INDEX + 1) * args.vectors]
    # the same records with their command and position: the tolerance's cost on full records on time
    runs["clean_full"] = [read(model, contract, c, c.record, tolerance) for c in cases]
    print(json.dumps({"clean_full": tally(runs["clean_full"]), "s": round(time.perf_counter() - t0)}), flush=True)
    for delay in DELAYS_MS:
        lag = round(delay * 1e-3 * rate)
        key = f"current_only_{delay:+g}ms"
        runs[key] = [
            read(model, contract, c, Record(c.record.time, None, None, delayed(c.record.current, lag)), tolerance)
            for c in cases
        ]
        print(json.dumps({key: tally(runs[key]), "s": round(time.perf_counter() - t0)}), flush=True)
    for delay in FULL_DELAYS_MS:
        lag = round(delay * 1e-3 * rate)
        key = f"full_current_alone_{delay:+g}ms"
        runs[key] = [
            read(
                model,
                contract,
                c,
                Record(c.record.time, c.record.command, c.record.position, delayed(c.record.current, lag)),
                tolerance,
            )
            for c in cases
        ]
        print(json.dumps({key: tally(runs[key]), "s": round(time.perf_counter() - t0)}), flush=True)
    for key, rows in runs.items():
        report["cases"][key] = {"as_shipped": tally(rows), **{f"at_{t:g}": tally(rows, t) for t in THRESHOLDS}}
    ratios = np.array([r["ratio"] for r in runs["clean"] if r["ratio"] is not None and abs(r["shift_s"]) >= 3e-4])
    report["clean_ratio_far_shift"] = {
        "records": len(runs["clean"]),
        "far": int(ratios.size),
        "quantiles": {q: float(np.quantile(ratios, q)) for q in (0.5, 0.99, 0.997)} if ratios.size else None,
        "max": float(ratios.max()) if ratios.size else None,
        "above_default": int((ratios >= TIMING_RATIO).sum()),
    }
    report["wall_s"] = round(time.perf_counter() - t0, 1)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    write_json(args.out, report)
    print(f"wrote {args.out} in {report['wall_s']} s")
    return report


if __name__ == "__main__":
    main()
