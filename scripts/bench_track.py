"""Speed of the life tracker (issue 25): one inspection update of one actuator, and a fleet of actuators x
inspections: the pipeline's batched diagnosis of records in memory, then the filter; CSV reading on its own.

    python scripts/bench_track.py [--actuators 1000] [--inspections 50] [--repeats 3] [--threads 1] [--chunk-size 64]

Writes scripts/bench_track.json. The pipeline runs on simulated HF records with 0.5 % noise (a pool reused
across inspections), so its batched cost is that of real ones. The filter is fed wearing actuators: each one's
k follows the damage law from a small random start at its own rate scale s (lognormal, the law's sigma), its
k_hat is that k plus the calibrated error and its verdict the pipeline's classifier, so the RUL searches and
the warm starts are those of a real life (a constant record would leave every particle censored, the
cheapest case).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import statistics
import time
from pathlib import Path

import torch
import yaml

from phm_torch.command import Chirp
from phm_torch.faults import FAULT_NAMES
from phm_torch.io import read_measurement, write_measurement
from phm_torch.online.export import read_metadata
from phm_torch.online.input_contract import InputContract
from phm_torch.params import CONF_DIR, load_actuator
from phm_torch.simulator import EMASimulator
from phm_torch.tracking import Inspection, TrackerSettings, build_tracker, track_fleet
from phm_torch.tracking.inspection import inspect_currents
from phm_torch.tracking.measurement import interval_scale
from phm_torch.tracking.near_nominal import NearNominalFDI

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


def wearing_fleet(model, law, n_actuators: int, n_inspections: int, seed: int = 0) -> list:
    """Per actuator, per inspection (k_hat (1, 8), scale (1, 8), faulty (1,)) of a wearing actuator: k from the
    damage law (initial damage up to 0.01, s lognormal), k_hat = k + the calibrated error, clamped."""
    g = torch.Generator().manual_seed(seed)
    s = torch.exp(law.rate_scale_sigma * torch.randn(n_actuators, generator=g, dtype=torch.float64))
    k0 = law.nominal.repeat(n_actuators, 1)
    k0[:, :6] = 0.01 * torch.rand(n_actuators, 6, generator=g, dtype=torch.float64)
    out = [[] for _ in range(n_actuators)]
    for i in range(n_inspections):
        k = law.nominal + law.propagate(k0 - law.nominal, s * 200.0 * i)
        lo, hi = model.k_interval(k.to(model.times.dtype))
        scale = interval_scale(k, lo.double(), hi.double(), math.inf)
        k_hat = (k + scale * torch.randn(k.shape, generator=g, dtype=torch.float64)).clamp(0.0, 1.0)
        with torch.no_grad():
            faulty = model.classifier(k_hat.to(model.times.dtype)) <= model.classifier.threshold
        for a in range(n_actuators):
            out[a].append((k_hat[a : a + 1], scale[a : a + 1], faulty[a : a + 1]))
    return out


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--actuators", type=int, default=1000)
    ap.add_argument("--inspections", type=int, default=50)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--pool", type=int, default=256)
    ap.add_argument(
        "--chunk-size",
        type=int,
        default=None,
        help="actuators filtered together (default: phm-track's, conf/track.yaml chunk_size)",
    )
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    model = torch.jit.load(str(PIPELINE))
    metadata = read_metadata(PIPELINE)
    damage = yaml.safe_load((CONF_DIR / "damage" / "coupled.yaml").read_text())
    settings = TrackerSettings()
    # the chunk phm-track filters together: smaller batches of particles stay in cache (1,000 actuators at once:
    # 1.4 ms per update; 64, the app's default: 1.0 ms, measured on 400 x 50)
    chunk_size = args.chunk_size or int(yaml.safe_load((CONF_DIR / "track.yaml").read_text())["chunk_size"])
    out: dict = {
        "pipeline": str(PIPELINE.relative_to(ROOT)),
        "threads": args.threads,
        "chunk_size": chunk_size,
        "settings": vars(settings),
        "machine": {
            "cpus": os.cpu_count(),
            # the host is shared: the load averages say whether other jobs ran beside the benchmark (~1: none)
            "load_average_start": os.getloadavg(),
        },
    }

    # one inspection update of one actuator (predict + fuse + RUL) along a wearing life, after its first
    tracker, _ = build_tracker(model, metadata, damage, settings, str(PIPELINE))
    life = wearing_fleet(model, tracker.law, 8, 40, seed=1)
    times = []
    for a in range(8):
        for i in range(40):
            k_hat, scale, faulty = life[a][i]
            t0 = time.perf_counter()
            tracker.update([f"S{a}"], torch.tensor([200.0 * i]), k_hat, scale, torch.tensor([True]), faulty)
            if i:
                times.append(time.perf_counter() - t0)
    times.sort()
    out["single_update_ms"] = {
        "p50": 1e3 * statistics.median(times),
        "p90": 1e3 * times[int(0.9 * len(times))],
        "updates": len(times),
    }

    # the near-nominal FDI's reading of one record (its coefficients, its network, the gate), where it ships
    pool = records(model, args.pool)
    near_path = PIPELINE.with_name(PIPELINE.stem + ".near_nominal.pt")
    near = NearNominalFDI.load(near_path) if near_path.is_file() else None
    if near is not None:
        one = pool[:1]
        with torch.no_grad():
            k_one, noise_one = model(one)[0], model.noise_level(one)
        reads_us = []
        for _ in range(200):
            t0 = time.perf_counter()
            with torch.no_grad():
                near.read(near.coefficients(model, one)[0], k_one, noise_one)
            reads_us.append(1e6 * (time.perf_counter() - t0))
        out["near_nominal_read_us_p50"] = statistics.median(reads_us)

    # CSV reading (the project's reader, one 10001-sample record)
    csv = ROOT / "scripts" / ".bench_track_record.csv"
    n = pool.shape[1]
    zeros = torch.zeros(n, dtype=torch.float64)
    write_measurement(
        csv,
        {
            "time": torch.arange(n, dtype=torch.float64) / float(model.sample_rate),
            "command": zeros,
            "position": zeros,
            "current": pool[0].double(),
        },
    )
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
    index = {
        f"A{a:04d}": [
            Inspection(f"A{a:04d}", 200.0 * i, f"r{i}", Path("."), "", i + 2) for i in range(args.inspections)
        ]
        for a in range(args.actuators)
    }
    runs = []
    for rep in range(args.repeats):
        t0 = time.perf_counter()
        diagnoses = []
        for start in range(0, total, 512):
            idx = torch.arange(start, min(total, start + 512)) % args.pool
            diagnoses += inspect_currents(model, pool[idx], contract, near)
        t_pipe = time.perf_counter() - t0
        tracker, _ = build_tracker(model, metadata, damage, settings, str(PIPELINE))
        # the filter's input: each actuator wearing along the law (k_hat, interval, verdict), the rest of each
        # diagnosis (snapshot RUL, noise) the pipeline's on the pool
        life = wearing_fleet(model, tracker.law, args.actuators, args.inspections, seed=rep)
        fed = {}
        for j, (a, r) in enumerate((a, r) for a, rows in index.items() for r in rows):
            k_hat, scale, faulty = life[int(a[1:])][r.line - 2]
            lo, hi = (k_hat - 1.645 * scale).clamp(0, 1)[0].tolist(), (k_hat + 1.645 * scale).clamp(0, 1)[0].tolist()
            fed[(a, r.line)] = {  # the near-nominal reading (timed above) replaced by the wearing k_hat too
                **{key: v for key, v in diagnoses[j].items() if not key.startswith("k_near_nominal")},
                "k_hat": dict(zip(FAULT_NAMES, k_hat[0].tolist())),
                "k_interval": {n: [x, y] for n, x, y in zip(FAULT_NAMES, lo, hi)},
                "healthy": not bool(faulty[0]),
                "out_of_distribution": False,
                "ood_reasons": [],
            }

        def diagnose(rows, fed=fed):
            return [fed[(r.actuator, r.line)] for r in rows]

        t1 = time.perf_counter()
        track_fleet(index, tracker, model, diagnose, None, None, chunk_size=chunk_size)
        t_filter = time.perf_counter() - t1
        runs.append({"pipeline_s": t_pipe, "filter_s": t_filter, "total_s": t_pipe + t_filter})
        print(json.dumps(runs[-1]), flush=True)
    out["fleet"] = {
        "actuators": args.actuators,
        "inspections": args.inspections,
        "runs": runs,
        "median_total_s": statistics.median(r["total_s"] for r in runs),
        "median_pipeline_s": statistics.median(r["pipeline_s"] for r in runs),
        "median_filter_s": statistics.median(r["filter_s"] for r in runs),
    }
    out["machine"]["load_average_end"] = os.getloadavg()
    (ROOT / "scripts" / "bench_track.json").write_text(json.dumps(out, indent=2) + "\n")
    print(json.dumps(out, indent=2))


if __name__ == "__main__":
    main()
