"""Speed of the life tracker (issue 25): one inspection update of one actuator, and a fleet of actuators x
inspections with records in memory batched through the pipeline; CSV reading measured on its own.

    python scripts/bench_track.py [--actuators 1000] [--inspections 50] [--repeats 3] [--threads 1]

Writes scripts/bench_track.json. Records are synthetic in-distribution currents (the pipeline's POD mean plus
small mode amplitudes; a pool reused across inspections), so the pipeline's batched cost is that of real ones.
"""

from __future__ import annotations

import argparse
import json
import statistics
import time
from pathlib import Path

import torch
import yaml

from phm_torch.command import Chirp
from phm_torch.io import read_measurement, write_measurement
from phm_torch.online.export import read_metadata
from phm_torch.online.input_contract import InputContract
from phm_torch.params import CONF_DIR, load_actuator
from phm_torch.simulator import EMASimulator
from phm_torch.tracking import Inspection, TrackerSettings, build_tracker, track_fleet
from phm_torch.tracking.inspection import inspect_currents
from phm_torch.tracking.measurement import interval_scale

ROOT = Path(__file__).resolve().parents[1]
PIPELINE = ROOT / "pretrained" / "online_surrogates_best.pt"


def records(model, n: int, seed: int = 0) -> torch.Tensor:
    """n noisy copies (n, n_full) of two simulated HF records (nominal; 10 % dry friction), 0.5 % white noise."""
    k = torch.tensor([[0.0] * 6 + [0.5, 0.5], [0.1] + [0.0] * 5 + [0.5, 0.5]], dtype=torch.float64)
    command = Chirp()
    sig = EMASimulator(load_actuator(), "hf").run(k, command, command.duration, channels=["current"])
    base = sig["current"][torch.arange(n) % 2]
    g = torch.Generator().manual_seed(seed)
    rms = base.pow(2).mean(1, keepdim=True).sqrt()
    return (base + 0.005 * rms * torch.randn(base.shape, generator=g, dtype=base.dtype)).to(model.times.dtype)


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--actuators", type=int, default=1000)
    ap.add_argument("--inspections", type=int, default=50)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--pool", type=int, default=256)
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    model = torch.jit.load(str(PIPELINE))
    metadata = read_metadata(PIPELINE)
    damage = yaml.safe_load((CONF_DIR / "damage" / "coupled.yaml").read_text())
    settings = TrackerSettings()
    out: dict = {"pipeline": str(PIPELINE.relative_to(ROOT)), "threads": args.threads, "settings": vars(settings)}

    # one inspection update of one actuator (predict + fuse + RUL), after its first
    tracker, _ = build_tracker(model, metadata, damage, settings, str(PIPELINE))
    k = torch.tensor([[0.05, 0.01, 0.0, 0.0, 0.0, 0.01, 0.5, 0.5]], dtype=torch.float64)
    lo, hi = model.k_interval(k.to(model.times.dtype))
    scale = interval_scale(k, lo.double(), hi.double(), settings.measurement_dof)
    times = []
    for i in range(60):
        t0 = time.perf_counter()
        tracker.update(["A"], torch.tensor([200.0 * i]), k * (1 + 0.02 * i), scale, torch.tensor([True]))
        times.append(time.perf_counter() - t0)
    out["single_update_ms"] = {"p50": 1e3 * statistics.median(times[5:]), "p90": 1e3 * sorted(times[5:])[int(0.9 * 55)]}

    # CSV reading (the project's reader, one 10001-sample record)
    pool = records(model, args.pool)
    csv = ROOT / "scripts" / ".bench_track_record.csv"
    n = pool.shape[1]
    zeros = torch.zeros(n, dtype=torch.float64)
    write_measurement(csv, {"time": torch.arange(n, dtype=torch.float64) / float(model.sample_rate),
                            "command": zeros, "position": zeros, "current": pool[0].double()})
    reads = []
    for _ in range(10):
        t0 = time.perf_counter()
        read_measurement(csv, expected_rate=float(model.sample_rate))
        reads.append(time.perf_counter() - t0)
    csv.unlink()
    per_csv = statistics.median(reads)
    total = args.actuators * args.inspections
    out["csv_read_ms_per_record"] = 1e3 * per_csv
    out["csv_read_s_fleet_extrapolated"] = per_csv * total

    # the fleet: pipeline (batched, records in memory) then the filter
    contract = InputContract.of(model, metadata, None)
    index = {f"A{a:04d}": [Inspection(f"A{a:04d}", 200.0 * i, f"r{i}", Path("."), "", i + 2)
                           for i in range(args.inspections)] for a in range(args.actuators)}
    runs = []
    for rep in range(args.repeats):
        t0 = time.perf_counter()
        diagnoses = []
        for start in range(0, total, 512):
            idx = torch.arange(start, min(total, start + 512)) % args.pool
            diagnoses += inspect_currents(model, pool[idx], contract)
        t_pipe = time.perf_counter() - t0
        order = {(a, r.line): j for j, (a, r) in enumerate((a, r) for a, rows in index.items() for r in rows)}

        def diagnose(rows, diagnoses=diagnoses, order=order):
            return [diagnoses[order[(r.actuator, r.line)]] for r in rows]

        tracker, _ = build_tracker(model, metadata, damage, settings, str(PIPELINE))
        t1 = time.perf_counter()
        track_fleet(index, tracker, model, diagnose, None, None, chunk_size=args.actuators)
        t_filter = time.perf_counter() - t1
        runs.append({"pipeline_s": t_pipe, "filter_s": t_filter, "total_s": t_pipe + t_filter})
        print(json.dumps(runs[-1]), flush=True)
    out["fleet"] = {"actuators": args.actuators, "inspections": args.inspections, "runs": runs,
                    "median_total_s": statistics.median(r["total_s"] for r in runs),
                    "median_pipeline_s": statistics.median(r["pipeline_s"] for r in runs),
                    "median_filter_s": statistics.median(r["filter_s"] for r in runs)}
    (ROOT / "scripts" / "bench_track.json").write_text(json.dumps(out, indent=2) + "\n")
    print(json.dumps(out, indent=2))


if __name__ == "__main__":
    main()
