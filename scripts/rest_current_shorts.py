"""Which faults draw current at rest? The input contract's ``offset`` check compares a record's rest window (the
leading samples where the nominal record has not left zero) with the nominal record's, and skips answers that
could draw current there (``rest_offset_check.REST_SHORTS``). Writes JSON.

HF records of the pipeline's actuator on its test command (noise-free, cached with the corruption suite's records)
over a grid of two-phase shorts (short_b x short_c) and of one short with dry friction or backlash and gain drift;
per vector the rest window's mean offset from the nominal record over ``OFFSET_MAX`` x the nominal RMS (1: the
check's limit, before its noise term).

    python scripts/rest_current_shorts.py [--pipeline pretrained/online_surrogates_best.pt] [--out results/rest.json]
"""

from __future__ import annotations

import argparse
import itertools
import json
from pathlib import Path

import torch

from phm_torch.faults import FAULT_NAMES
from phm_torch.io.atomic import atomic_open
from phm_torch.online.corruption_suite import CACHE, PIPELINE, _simulate, contract_of, pipeline_conditions
from phm_torch.online.loaded import load_pipeline
from phm_torch.online.rest_offset_check import OFFSET_MAX, rest_window

LEVELS = (0.2, 0.35, 0.5, 0.65, 0.8, 0.95)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--pipeline", default=str(PIPELINE))
    ap.add_argument("--out", default="results/rest_current_shorts.json")
    args = ap.parse_args()
    path = Path(args.pipeline)
    nominal = contract_of(load_pipeline(path), path).nominal
    scale = float(nominal.pow(2).mean().sqrt())
    rest = rest_window(nominal)
    params, _, command = pipeline_conditions(path)
    k0 = torch.tensor(params.nominal_faults, dtype=torch.float64)
    index = {name: i for i, name in enumerate(FAULT_NAMES)}
    rows = []
    for a, b in itertools.product(LEVELS, LEVELS):
        rows.append({"short_b": a, "short_c": b})
    for a in LEVELS:
        rows.append({"short_a": a, "dry_friction": 0.8})
        rows.append({"short_a": a, "backlash": 0.8, "gain_drift": 0.9})
    k = k0.repeat(len(rows), 1)
    for r, move in zip(k, rows):
        for name, value in move.items():
            r[index[name]] = value
    current = _simulate(params, k, command, CACHE, "rest_grid")["current"].double()
    ratio = (current[:, :rest] - nominal[:rest]).mean(1).abs() / (OFFSET_MAX * scale)
    report = {
        "pipeline": str(path),
        "rest_samples": rest,
        "limit_a": OFFSET_MAX * scale,
        "vectors": [{**move, "offset_over_limit": float(v)} for move, v in zip(rows, ratio)],
    }
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    with atomic_open(out, "w") as fh:
        fh.write(json.dumps(report, indent=2))
    for move, v in zip(rows, ratio):
        print(move, round(float(v), 3))


if __name__ == "__main__":
    main()
