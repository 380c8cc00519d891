"""Simulator throughput (signals/s) and peak memory versus batch size, for HF and LF; writes JSON.

Each configuration runs in its own process so that its peak resident memory is its own. A run
simulates the 0.5 s test chirp for a batch of random fault vectors, streaming the batch in chunks
of ``--chunk`` (so memory is bounded at any batch size) and keeping the envelope current and the
position in float32, as dataset generation does. Reported: median wall time of ``--repeats`` runs
after a warm-up (the warm-up includes ``torch.compile``'s one-off compilation, reported separately).

Usage: python scripts/bench_simulate.py [--out results/bench_simulate.json] [--quick]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import resource
import statistics
import subprocess
import sys
import time
from pathlib import Path


def one(fidelity: str, batch: int, chunk: int, compile: bool, repeats: int, duration: float, threads: int) -> dict:
    import torch

    from phm_torch.command import Chirp
    from phm_torch.params import load_actuator
    from phm_torch.simulator import EMASimulator

    torch.set_num_threads(threads)
    p = load_actuator()
    g = torch.Generator().manual_seed(0)
    k = torch.rand(batch, 8, generator=g, dtype=torch.float64) ** 8
    sim = EMASimulator(p, fidelity, compile=compile)
    cmd = Chirp(duration=duration)
    kw = {"channels": ["current", "position"], "out_dtype": torch.float32}
    t0 = time.perf_counter()
    for _ in sim.iter_chunks(k[: min(chunk, batch)], cmd, 0.002, chunk, **kw):
        pass
    warmup = time.perf_counter() - t0
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        n = 0
        for s in sim.iter_chunks(k, cmd, duration, chunk, **kw):
            n += s["current"].shape[0]
        times.append(time.perf_counter() - t0)
    med = statistics.median(times)
    return {
        "fidelity": fidelity,
        "batch": batch,
        "chunk": chunk,
        "compile": compile,
        "threads": threads,
        "duration_s": duration,
        "repeats": repeats,
        "wall_s": times,
        "median_wall_s": med,
        "signals_per_s": batch / med,
        "warmup_s": warmup,
        "peak_rss_gb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1e6,
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--out", default="results/bench_simulate.json")
    ap.add_argument("--quick", action="store_true", help="small batches only (a smoke run)")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--child", nargs=5, metavar=("FID", "BATCH", "CHUNK", "COMPILE", "DURATION"))
    args = ap.parse_args()
    if args.child:
        fid, batch, chunk, comp, dur = args.child
        print(json.dumps(one(fid, int(batch), int(chunk), comp == "1", args.repeats, float(dur), args.threads)))
        return
    if args.quick:
        plan = [("lf", 16, 16, 0, 1), ("hf", 16, 16, 0, 1)]
    else:
        plan = [
            ("lf", 1, 1, 0, 3),
            ("lf", 256, 256, 0, 3),
            ("lf", 2048, 2048, 1, 3),
            ("lf", 16384, 4096, 1, 1),
            ("hf", 1, 1, 0, 1),
            ("hf", 256, 256, 1, 1),
            ("hf", 2048, 2048, 1, 3),
            ("hf", 8192, 4096, 1, 1),
        ]
    results = []
    for fid, batch, chunk, comp, reps in plan:
        cmd = [
            sys.executable,
            __file__,
            "--child",
            fid,
            str(batch),
            str(chunk),
            str(comp),
            "0.5",
            "--repeats",
            str(min(reps, args.repeats)),
            "--threads",
            str(args.threads),
        ]
        out = subprocess.run(cmd, capture_output=True, text=True, check=True, env=os.environ.copy())
        res = json.loads(out.stdout.strip().splitlines()[-1])
        print(
            f"{fid} B={batch:6d} chunk={chunk:5d} compile={comp}: {res['signals_per_s']:8.1f} signals/s, "
            f"peak {res['peak_rss_gb']:.2f} GB",
            flush=True,
        )
        results.append(res)
    best = {f: max(r["signals_per_s"] for r in results if r["fidelity"] == f) for f in ("hf", "lf")}
    report = {
        "machine": {
            "platform": platform.platform(),
            "processor": platform.processor(),
            "cpus": os.cpu_count(),
            "python": platform.python_version(),
        },
        "results": results,
        "best_signals_per_s": best,
        "lf_over_hf": best["lf"] / best["hf"],
        "peak_rss_gb_max": max(r["peak_rss_gb"] for r in results),
        "targets": {"hf_signals_per_s": 30, "lf_over_hf": 10, "peak_rss_gb": 4},
    }
    path = Path(args.out)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(".tmp")
    tmp.write_text(json.dumps(report, indent=2))
    os.replace(tmp, path)
    print(json.dumps({k: report[k] for k in ("best_signals_per_s", "lf_over_hf", "peak_rss_gb_max")}))


if __name__ == "__main__":
    main()
