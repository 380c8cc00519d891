"""Speed of phm-predict's per-record diagnosis (``phm_torch.online.diagnosis.diagnose``): every check a record
passes through, the pipeline's step and the ``timing`` check's scan on their own; writes JSON.

    python scripts/bench_diagnose.py [--pipeline pretrained/online_surrogates_best.pt] [--repeats 5]
        [--threads 1] [--out scripts/bench_diagnose.json]

The records are the corruption suite's (``suite_records``: HF simulations of the pipeline's own actuator and command,
from its provenance): nominal, dry friction x1.6, 40 % of phase A shorted, and backlash x20 with a gain drift, each
at 1 % noise, current-only (the
paper's input: the timing check runs) and with their command and position (the command and tracking checks run,
a trigger offset is looked for). Each figure is the median over ``--repeats`` passes of every record (CSV reading
excluded: scripts/bench_track.py measures it).
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import platform
import statistics
import time
from pathlib import Path
from typing import Any

import torch

from phm_torch.io.atomic import write_json
from phm_torch.online.corruption_suite import CACHE, PIPELINE, contract_of, suite_records
from phm_torch.online.corruptions import Record
from phm_torch.online.diagnosis import diagnose
from phm_torch.online.loaded import load_pipeline
from phm_torch.online.timing_check import scan_shifts, timing_scan


def pass_ms(fn: Any, items: list[Any], repeats: int) -> dict[str, float]:
    """Median and worst [ms] per item over ``repeats`` passes of ``fn(item)`` on every item (one warm-up pass)."""
    for item in items:
        fn(item)
    per_item = []
    for _ in range(repeats):
        for item in items:
            t0 = time.perf_counter()
            fn(item)
            per_item.append(1e3 * (time.perf_counter() - t0))
    return {"p50_ms": statistics.median(per_item), "max_ms": max(per_item), "calls": len(per_item)}


def main(argv: list[str] | None = None) -> dict[str, Any]:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--pipeline", type=Path, default=PIPELINE)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--cache", type=Path, default=CACHE)
    ap.add_argument("--out", type=Path, default=Path(__file__).with_suffix(".json"))
    args = ap.parse_args(argv)
    if args.repeats < 1:
        raise ValueError(f"--repeats must be >= 1, got {args.repeats}")
    if args.threads < 1:
        raise ValueError(f"--threads must be >= 1, got {args.threads}")
    torch.set_num_threads(args.threads)
    load_start = os.getloadavg()
    model = load_pipeline(str(args.pipeline))
    scripted = torch.jit.load(str(args.pipeline))
    contract = contract_of(scripted, args.pipeline)
    full = [case.record for case in suite_records(scripted, args.pipeline, args.cache, simulated=False)[0]]
    current_only = [Record(r.time, None, None, r.current) for r in full]
    untimed = dataclasses.replace(contract, timing_ratio=None)
    currents = [r.current.to(model.dtype).reshape(1, -1) for r in full]
    noise = [float(model.noise_level(c)[0]) for c in currents]
    with torch.no_grad():
        out: dict[str, Any] = {
            "pipeline": str(args.pipeline),
            "records": len(full),
            "samples": int(model.n_full),
            "timing_scan_grid": len(scan_shifts(int(model.n_full))),  # the shifts it may read (coarse to fine: ~71)
            "threads": args.threads,
            "repeats": args.repeats,
            "diagnose_current_only": pass_ms(lambda r: diagnose(model, r, contract), current_only, args.repeats),
            "diagnose_current_only_without_timing": pass_ms(
                lambda r: diagnose(model, r, untimed), current_only, args.repeats
            ),
            "diagnose_full_record": pass_ms(lambda r: diagnose(model, r, contract), full, args.repeats),
            "pipeline_step": pass_ms(lambda c: model.run(c, None), currents, args.repeats),
            "timing_scan": pass_ms(
                lambda i: timing_scan(model, currents[i][0], noise[i]), list(range(len(full))), args.repeats
            ),
        }
    out["machine"] = {
        "cpus": os.cpu_count(),
        "processor": platform.processor() or platform.machine(),
        "torch": torch.__version__,
        # the host is shared: the load averages say whether other jobs ran beside the benchmark (~1: none)
        "load_average_start": load_start,
        "load_average_end": os.getloadavg(),
    }
    write_json(args.out, out)
    print(
        f"diagnose (current only) {out['diagnose_current_only']['p50_ms']:.1f} ms, of which the timing scan "
        f"{out['timing_scan']['p50_ms']:.1f} ms; with command and position {out['diagnose_full_record']['p50_ms']:.1f}"
        f" ms; the pipeline's step {out['pipeline_step']['p50_ms']:.2f} ms. Wrote {args.out}"
    )
    return out


if __name__ == "__main__":
    main()
