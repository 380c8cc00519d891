"""Give an exported pipeline that lacks it the tracker check phm-run's companions stage writes beside its pipeline:
the life tracker's figures on run-to-failure histories with their truth (``<stem>.tracker_check.json``, which
phm-track reads with ``tracker_check=auto``, warning where a figure falls short) and the end-of-life rule chosen on
them (phm-track's ``verdict=auto`` / ``faulty_at=auto`` read it there when the near-nominal FDI records none).

The shipped pretrained pipeline's companions (FDI response, near-nominal FDI) were made by hand before the stage
existed, so phm-track ran it under its default rule with no figures to warn from. This script tracks a life split of
the pipeline's actuator and command (the truth's records checked against the pipeline's) under each rule of the
stage (:data:`~phm_torch.apps.run_companions.RULES`) with the companion files beside the pipeline, exactly as the
stage does (:func:`~phm_torch.apps.run_companions.check_tracker`), and writes the check beside the pipeline. Give it histories nothing was fitted on (another seed than the near-nominal
FDI's life split): the figures are then what a new fleet will see, not the training split's.

    phm-generate stage=life dataset.life.n_actuators=100 seed=35 data_dir=/tmp/life35 threads=1     # ~10 min
    python scripts/add_tracker_check.py --pipeline pretrained/online_surrogates_best.pt --life /tmp/life35/life \
        --work-dir /tmp/check35

Writes ``<work dir>/tracker_rules.json`` (every rule's figures, the one chosen) beside the tracks.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import torch

from phm_torch import provenance
from phm_torch.apps.run_companions import LATE_WEIGHT, check_tracker, companion_paths
from phm_torch.io.atomic import write_json
from phm_torch.online.export import read_metadata
from phm_torch.tracking.near_nominal import NearNominalFDI


def life_files(life: Path, pipeline: Path) -> tuple[Path, Path]:
    """The life split's index and truth; a clear error where either is missing, or where the truth records another
    actuator or test command than the pipeline's (phm-track only warns of that; a check measured on another
    actuator's histories would be written beside the pipeline as its own)."""
    index, truth = life / "index.csv", life / "truth.json"
    for path in (index, truth):
        if not path.is_file():
            raise ValueError(
                f"--life: {life} holds no {path.name} (a folder phm-generate stage=life wrote: <data_dir>/life)"
            )
    recorded = json.loads(truth.read_text())
    made_for = read_metadata(pipeline).get("provenance") or {}
    provenance.require_same({key: recorded.get(key) for key in provenance.KEYS}, made_for, f"life split {life}")
    return index, truth


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument(
        "--pipeline", required=True, type=Path, help="the exported pipeline (the check is written beside it)"
    )
    ap.add_argument("--life", required=True, type=Path, help="a life split of its actuator and command, with truth")
    ap.add_argument("--work-dir", required=True, type=Path, help="where the tracks under each rule are written")
    ap.add_argument("--late-weight", type=float, default=LATE_WEIGHT, help="a late interval counts this many early")
    ap.add_argument("--threads", type=int, default=1)
    args = ap.parse_args(argv)
    if not args.pipeline.is_file():
        raise ValueError(f"--pipeline: {args.pipeline} does not exist")
    index, truth = life_files(args.life, args.pipeline)
    torch.set_num_threads(args.threads)
    near_path = companion_paths(args.pipeline)["near_nominal"]
    near = NearNominalFDI.load(near_path) if near_path.is_file() else None
    if near is not None and near.provenance.get("tracker_rule"):
        # phm-track would read that rule, not the one chosen here: the check would describe another tracker
        raise ValueError(
            f"{near_path} records its own end-of-life rule; phm-run's companions stage made this pipeline's check"
        )
    life_args = [f"index={index}", f"pipeline={args.pipeline}", f"truth={truth}", f"threads={args.threads}"]
    chosen, check = check_tracker(
        args.pipeline, life_args, args.work_dir, "auto" if near is not None else "null", args.late_weight
    )
    report = {
        "pipeline": str(args.pipeline),
        "life": str(args.life),
        "near_nominal": None if near is None else str(near_path),
        "tracker_rule": chosen,
        **check,
    }
    write_json(args.work_dir / "tracker_rules.json", report)
    print(json.dumps(report, indent=2))
    return report


if __name__ == "__main__":
    main()
