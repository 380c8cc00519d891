"""What the bench corrections do on clean val-like records of a pipeline's actuator, on phm-predict's path: a mains hum
added, each record read as it is and with its lines removed (``phm_torch.online.bench_lines``); a probe offset of
random sign and coloured noise added, read as the code reads them (the rest-window offset removal,
``phm_torch.online.diagnosis.remove_probe_offset``). Writes JSON: per case the right / wrong unflagged and flagged
counts, and how many of the clean records (0-3 % noise) had a line removed.

    python scripts/record_corrections_eval.py [--pipeline pretrained/online_surrogates_best.pt] [--vectors 500]
        [--out docs/trust/record_corrections_pretrained.json]

The HF records are the corruption suite's clean ones (simulated once, cached under ``--cache``).
"""

from __future__ import annotations

import json
import math
import time
from pathlib import Path
from typing import Any

import numpy as np
import torch

from phm_torch.io.atomic import write_json
from phm_torch.online.corruption_suite import Case, clean_record_arguments, clean_records, contract_of, judge
from phm_torch.online.corruptions import Record, corrupt
from phm_torch.online.diagnosis import diagnose

HUMS = ((0.0, 400.0), (0.05, 400.0), (0.2, 400.0), (0.4, 400.0), (0.2, 60.0), (0.2, 1234.5))  # (share, Hz)
OFFSETS = (0.02, 0.05, 0.1, 0.25, 0.5)  # probe offsets, of the RMS current
COLOURED = (0.05, 0.1, 0.2)  # coloured noise (the corruption suite's kind), of the RMS current
NOISE_INDEX = 2  # the clean records come at 0, 1, 2, 3 % noise, each twice: the first 1 % draw


def with_hum(record: Record, share: float, frequency: float, phase: float) -> Record:
    """The record with a hum of ``share`` x its RMS current at ``frequency`` [Hz] added to its current."""
    current = record.current
    if share == 0.0:
        return record
    rms = float(current.pow(2).mean().sqrt())
    t = record.time - record.time[0]
    tone = torch.sin(2.0 * math.pi * frequency * t + phase).to(current.dtype)
    return Record(record.time, record.command, record.position, current + share * rms * tone)


def with_offset(record: Record, share: float, sign: float) -> Record:
    """The record with a probe offset of ``sign`` x ``share`` x its RMS current."""
    rms = float(record.current.pow(2).mean().sqrt())
    return Record(record.time, record.command, record.position, record.current + sign * share * rms)


def tally(model: Any, path: Path, cases: list[Case], records: list[Record], remove: bool = True) -> dict[str, Any]:
    """The judgement counts of ``records`` (one per case, corrupted) on phm-predict's path."""
    contract = contract_of(model, path)
    out = [judge(model, c, r, contract, remove_lines=remove) for c, r in zip(cases, records)]
    return {
        "cases": len(out),
        "right_unflagged": sum(not r["flagged"] and r["right"] for r in out),
        "wrong_unflagged": sum(not r["flagged"] and not r["right"] for r in out),
        "flagged": sum(r["flagged"] for r in out),
        "err_k_median": float(np.median([r["err_k"] for r in out])),
    }


def main(argv: list[str] | None = None) -> dict[str, Any]:
    args = clean_record_arguments(__doc__.splitlines()[0], "record_corrections.json").parse_args(argv)
    if args.vectors < 1:
        raise ValueError(f"--vectors must be >= 1, got {args.vectors}")
    torch.set_num_threads(1)
    t0 = time.perf_counter()
    model = torch.jit.load(str(args.pipeline))
    clean = clean_records(model, args.pipeline, args.vectors, args.cache)
    cases = clean[NOISE_INDEX * args.vectors : (NOISE_INDEX + 1) * args.vectors]
    report: dict[str, Any] = {"pipeline": str(args.pipeline), "noise": 0.01, "hums": []}
    phases = np.random.default_rng(7).uniform(0.0, 2.0 * math.pi, len(cases))
    for share, frequency in HUMS:
        row: dict[str, Any] = {"share": share, "frequency_hz": frequency}
        humming = [with_hum(c.record, share, frequency, float(p)) for c, p in zip(cases, phases)]
        for remove in (False, True):
            row["removed" if remove else "as_read"] = tally(model, args.pipeline, cases, humming, remove)
        report["hums"].append(row)
        print(json.dumps(row), flush=True)
    signs = np.random.default_rng(11).choice([-1.0, 1.0], len(cases))
    report["offsets"] = []
    for share in OFFSETS:
        shifted = [with_offset(c.record, share, float(s)) for c, s in zip(cases, signs)]
        report["offsets"].append({"share": share, **tally(model, args.pipeline, cases, shifted)})
        print(json.dumps(report["offsets"][-1]), flush=True)
    report["coloured_noise"] = []
    for share in COLOURED:
        noisy = [
            corrupt("coloured_noise", c.record, share, np.random.default_rng(1000 + i)) for i, c in enumerate(cases)
        ]
        report["coloured_noise"].append({"share": share, **tally(model, args.pipeline, cases, noisy)})
        print(json.dumps(report["coloured_noise"][-1]), flush=True)
    contract = contract_of(model, args.pipeline)
    removed = [c.k.tolist() for c in clean if diagnose(model, c.record, contract)["bench_lines"]]
    report["clean"] = {"records": len(clean), "lines_removed": len(removed), "fault_vectors": removed[:20]}
    report["wall_s"] = round(time.perf_counter() - t0, 1)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    write_json(args.out, report)
    print(f"clean records with a line removed: {len(removed)} of {len(clean)}; wrote {args.out}")
    return report


if __name__ == "__main__":
    main()
