"""Recalibrate the consistency check's thresholds of an exported TorchScript pipeline at another quantile.

The check's thresholds are a quantile of the in-distribution statistic at each calibrated noise level
(:func:`phm_torch.online.consistency.calibrate_consistency`, as phm-evaluate calibrates them). Each of the
pipeline's checks flags its own share of clean records and the flags add up; this script moves only the
consistency check's share (e.g. the shipped file from 0.995 to 0.998), on held-out records of a store of the
pipeline's actuator and command, and writes the pipeline with its metadata kept. The forward surrogate and
everything else are unchanged. Reports the flagged shares of the store's other records before and after.

    python scripts/recalibrate_consistency.py --pipeline pretrained/online_surrogates_best.pt \
        --data-dir /tmp/cal8k --quantile 0.998 --out /tmp/recal/online.pt
    phm-export pipeline=/tmp/recal/online.pt format=[torchscript,export] out=/tmp/recal/ship/online_surrogates_best.pt
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import torch

from phm_torch import provenance
from phm_torch.data import DatasetStore
from phm_torch.online.consistency import recalibrate_consistency
from phm_torch.online.export import export_torchscript
from phm_torch.online.from_torchscript import pipeline_from_torchscript


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--pipeline", required=True, help="a TorchScript pipeline file with a consistency check")
    ap.add_argument("--data-dir", required=True, help="a store of the pipeline's actuator and command")
    ap.add_argument("--split", default="val", help="the store's split: its first --calibrate-records calibrate")
    ap.add_argument("--calibrate-records", type=int, default=6000)
    ap.add_argument("--quantile", type=float, required=True)
    ap.add_argument("--seed", type=int, default=13)
    ap.add_argument("--out", required=True)
    args = ap.parse_args(argv)
    pipe, metadata = pipeline_from_torchscript(args.pipeline)
    if not pipe.has_consistency:
        raise ValueError(f"--pipeline {args.pipeline}: it has no consistency check (scripts/add_consistency_check.py)")
    with DatasetStore(args.data_dir) as store:
        provenance.require_same(store.provenance or {}, metadata.get("provenance") or {}, f"store {args.data_dir}")
        view = store.split(args.split)
        x = torch.as_tensor(np.asarray(view.current[:]), dtype=torch.float32)
    old = metadata.get("consistency")
    result = recalibrate_consistency(pipe, x, args.quantile, args.seed, args.calibrate_records)
    export_torchscript(pipe, args.out, {**metadata, "consistency": result["after"]["calibration"]})
    report = {
        "out": args.out,
        "calibrate_records": args.calibrate_records,
        "check_records": len(x) - args.calibrate_records,
        "before": {"calibration": old, **result["before"]},
        "after": result["after"],
    }
    Path(args.out).with_suffix(".consistency.json").write_text(json.dumps(report, indent=2))
    print(json.dumps(report, indent=2))
    return report


if __name__ == "__main__":
    main()
