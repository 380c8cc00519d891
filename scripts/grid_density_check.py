"""Do a store's health labels depend on the sweep grid's density? Relabel vectors near the boundary at another density.

The bandwidth and the gain margin are read between grid points (``assessment.sweep.design.points_per_decade``,
default 12), so near the boundary the grid can decide a label. This script takes the vectors of a split where that
matters most and labels them again with the store's own assessment config at another density:

* with ``--bundle``: the bundle's health-classifier errors on the split and as many correctly classified vectors
  nearest its boundary (how many of the errors are the labels'?);
* without: the ``--n`` vectors whose measured margins lie nearest the requirements (relative distance, the
  smallest of the three).

    python scripts/grid_density_check.py --data-dir /tmp/heldout --bundle results/run/train/surrogates.pt \
        --points-per-decade 36 --out grid36.json

``--max-extensions`` and ``--refine`` relabel with the responses extended until they settle and measured again at
each vector's crossings (docs/dataset.md, "Settling and refinement"): how much of a store's labels hang on the
sweep's reading. Only an ``auto`` frequency grid has a density; a store whose grid was given as a list is refused. Writes counts of
changed labels as JSON (docs/own_actuator.md §4: keep the denser grid if they change often).
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path
from typing import Any

import numpy as np
import torch

from phm_torch.data.labels import LabelComputer
from phm_torch.data.store import DatasetStore, recorded_assessment
from phm_torch.io.atomic import write_json
from phm_torch.surrogates.bundle import SurrogateBundle


def assessment_at(metadata: dict[str, Any], points_per_decade: float, max_extensions: int = 0, refine: int = 0) -> Any:
    """The store's assessment function (its recorded actuator and config) with the grid at another density and,
    where given, the responses extended until they settle and refined at each vector's crossings."""
    sweep = ((metadata.get("config") or {}).get("assessment") or {}).get("sweep") or {}
    if sweep.get("frequencies", "auto") != "auto":
        raise ValueError(
            f"assessment.sweep.frequencies of the store is a list ({sweep.get('frequencies')!r}): it has no density"
        )
    changes: dict[str, Any] = {
        "design": {**(sweep.get("design") or {}), "points_per_decade": float(points_per_decade)},
        "compile": False,  # a few hundred vectors: compiling costs more than it saves
    }
    if max_extensions:
        changes["max_extensions"] = int(max_extensions)
    if refine:
        changes["refine"] = int(refine)
    return recorded_assessment(metadata, "cpu", changes)


def boundary_distance(margins: np.ndarray, requirements: dict[str, float], nominal_bandwidth: float) -> np.ndarray:
    """(N,) smallest relative distance of PM, GM and bandwidth from their requirements; a margin not measurable on
    the grid (nan) is no distance (the vector's label does not hang on a reading between grid points there)."""
    pm = np.abs(margins[:, 1] - requirements["phase_margin_deg"]) / requirements["phase_margin_deg"]
    gm = np.abs(margins[:, 3] - requirements["gain_margin_db"]) / max(requirements["gain_margin_db"], 1e-9)
    bw_req = requirements["bandwidth_fraction"] * nominal_bandwidth
    bw = np.abs(margins[:, 4] - bw_req) / bw_req
    return np.fmin(np.fmin(pm, gm), bw)  # fmin: a nan distance loses to any number; all nan stays nan (last)


def check(
    data_dir: str,
    points_per_decade: float,
    split: str,
    bundle: str | None,
    n: int,
    max_extensions: int = 0,
    refine: int = 0,
) -> dict[str, Any]:
    with DatasetStore(data_dir) as store:
        metadata = store.metadata
        group = store.split(split)  # a ValueError naming the splits if absent
        k = np.asarray(group.K)
        healthy = np.asarray(group.healthy).astype(bool)
        margins = np.asarray(group.margins)
        provenance = store.provenance
    assessment, params = assessment_at(metadata, points_per_decade, max_extensions, refine)
    report: dict[str, Any] = {"store": data_dir, "split": split, "points_per_decade": points_per_decade}
    # the settings in force: a store generated with them keeps them where the arguments leave them at 0
    report |= {"max_extensions": assessment.sweep.max_extensions, "refine": assessment.sweep.refine}
    if bundle is not None:
        b = SurrogateBundle.load(bundle)
        b.check_store(provenance, f"store {data_dir}")
        score = b.health_score(torch.as_tensor(k, dtype=torch.float64)).numpy()
        pred = score > 0
        errors = np.flatnonzero(pred != healthy)
        correct = np.flatnonzero(pred == healthy)
        near = correct[np.argsort(np.abs(score[correct]))[: len(errors)]]
        groups = {"errors": errors, "correct_nearest_boundary": near}
    else:
        req = dict(vars(assessment.requirements))
        # the store's margins are judged against the nominal bandwidth they were labelled with (the manifest's), not
        # the relabelling's: another reading moves it, and with it which vectors look nearest the requirements
        recorded = ((metadata.get("assessment_sweep") or {}).get("nominal_margins") or {}).get("bandwidth_hz")
        nominal_bw = float(recorded) if recorded is not None else assessment.nominal_bandwidth_hz
        dist = boundary_distance(margins, req, nominal_bw)
        order = np.argsort(np.where(np.isnan(dist), np.inf, dist), kind="stable")
        groups = {"nearest_requirements": order[:n]}
    rows = np.concatenate(list(groups.values()))
    if len(rows) == 0:
        raise ValueError(f"nothing to relabel in split {split!r} of {data_dir!r}")
    t0 = time.perf_counter()
    relabelled = LabelComputer(assessment, params.nominal_faults, len(rows))(k[rows])["healthy"].astype(bool)
    report["assess_s"] = round(time.perf_counter() - t0, 1)
    report["frequencies"] = len(assessment.sweep.frequencies)
    report["settling"] = assessment.settling()
    start = 0
    for name, idx in groups.items():
        new = relabelled[start : start + len(idx)]
        start += len(idx)
        report[name] = {"n": len(idx), "changed": int((new != healthy[idx]).sum())}
        if name == "errors":
            missed = pred[idx] & ~healthy[idx]
            report[name]["missed_faults"] = int(missed.sum())
            report[name]["missed_faults_changed"] = int((missed & (new != healthy[idx])).sum())
    return report


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data-dir", required=True, help="a store (phm-generate) with labels")
    ap.add_argument("--points-per-decade", type=float, default=36.0, help="the density to relabel at")
    ap.add_argument("--split", default="labels", help="the split whose vectors are relabelled")
    ap.add_argument("--bundle", default=None, help="relabel this bundle's classifier errors and its nearest correct")
    ap.add_argument("--n", type=int, default=200, help="without --bundle: vectors nearest the requirements")
    ap.add_argument(
        "--max-extensions",
        type=int,
        default=0,
        help="extend unsettled responses up to N times (0: as the store was labelled)",
    )
    ap.add_argument(
        "--refine",
        type=int,
        default=0,
        help="rounds of measurement at each vector's crossings (0: as the store was labelled)",
    )
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--out", default=None, help="JSON report (default: print only)")
    args = ap.parse_args()
    if not args.points_per_decade > 0:
        raise SystemExit(f"grid_density_check: error: --points-per-decade must be > 0, got {args.points_per_decade}")
    if args.n < 1:
        raise SystemExit(f"grid_density_check: error: --n must be >= 1, got {args.n}")
    for name in ("max_extensions", "refine"):
        if getattr(args, name) < 0:
            raise SystemExit(
                f"grid_density_check: error: --{name.replace('_', '-')} must be >= 0, got {getattr(args, name)}"
            )
    torch.set_num_threads(args.threads)
    try:
        report = check(
            args.data_dir, args.points_per_decade, args.split, args.bundle, args.n, args.max_extensions, args.refine
        )
    except ValueError as e:  # another actuator's store or bundle, a listed grid, a missing split: one line
        raise SystemExit(f"grid_density_check: error: {e}") from None
    if args.out:
        write_json(Path(args.out), report)
    print(json.dumps(report, indent=2))


if __name__ == "__main__":
    main()
