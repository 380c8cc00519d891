"""Benchmark of the paper-scale data generation (phm-generate experiment=paper); writes JSON.

Measures, with the shipped config (conf/generate.yaml + conf/experiment/paper.yaml):

* the assessment function: ms per fault vector amortised over a batch of ``chunk_size`` importance-
  sampled vectors (compiled, after a warm-up batch that pays the compilation), and the healthy fraction;
* the HF signals: signals/s at the batch ``chunk_size`` (compiled, after a warm-up batch);
* the extrapolated time of the full paper dataset: compilations + n_chunks x (signals + assessment);
* with ``--full DATA_DIR``: the real paper-scale generation, its wall time and CPU time.

Each timed part is repeated ``--repeat`` times; the JSON gives the median and every run. ``--override``
adds Hydra overrides to the composed config (e.g. ``+assessment.sweep.max_extensions=2``) to measure a
setting's cost; they are recorded.

Wall and CPU (user + system of this process) times are both recorded: on a shared machine the wall
time includes the waits for other processes.

Usage: python scripts/bench_generate.py [--out scripts/bench_generate.json] [--batches 2] [--repeat 3]
       [--override KEY=VALUE ...] [--full DIR]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import time
from pathlib import Path
from typing import Self

import torch
from hydra import compose, initialize_config_dir
from hydra.utils import instantiate
from omegaconf import OmegaConf

from phm_torch.apps.generate import generate
from phm_torch.data.generation import make_plan
from phm_torch.io.atomic import atomic_open
from phm_torch.params import CONF_DIR, ActuatorParams
from phm_torch.simulator import EMASimulator


class Clock:
    def __enter__(self) -> Self:
        self.wall, self.cpu = time.perf_counter(), time.process_time()
        return self

    def __exit__(self, *exc: object) -> None:
        self.wall = time.perf_counter() - self.wall
        self.cpu = time.process_time() - self.cpu


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default=str(Path(__file__).with_suffix(".json")))
    ap.add_argument("--batches", type=int, default=2, help="timed assessment batches (after the warm-up)")
    ap.add_argument("--full", default=None, help="also run phm-generate experiment=paper into this data_dir")
    ap.add_argument("--threads", type=int, default=None, help="torch intra-op threads (default: torch's)")
    ap.add_argument("--repeat", type=int, default=3, help="timed repetitions of each part (median reported)")
    ap.add_argument("--override", action="append", default=[], help="Hydra override of the composed config")
    args = ap.parse_args()
    if args.repeat < 1:
        raise ValueError(f"--repeat must be >= 1, got {args.repeat}")
    if args.batches < 1:
        raise ValueError(f"--batches must be >= 1, got {args.batches}")
    if args.threads:
        torch.set_num_threads(args.threads)

    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        cfg = compose("generate", ["experiment=paper", *args.override])
    params = ActuatorParams.from_mapping(OmegaConf.to_container(cfg.actuator, resolve=True))
    command = instantiate(cfg.command)
    spec = instantiate(cfg.dataset)
    assessment = instantiate(cfg.assessment, _partial_=True)(params=params)
    plan = make_plan(spec, params.nominal_faults, int(cfg.seed))
    cs = spec.chunk_size
    train = plan.K[plan.offsets["train"][0] : plan.offsets["train"][1]]
    out: dict = {
        "machine": {
            "cpus": os.cpu_count(),
            "torch_threads": torch.get_num_threads(),
            "platform": platform.platform(),
            "torch": torch.__version__,
            "load_avg_start": os.getloadavg(),
        },
        "config": {
            "chunk_size": cs,
            "rows": plan.n_rows,
            "chunks": plan.n_chunks,
            "test_frequencies": len(assessment.sweep.frequencies),
            "periods_per_vector": assessment.response.periods_per_vector,
            "overrides": args.override,
            "repeat": args.repeat,
        },
    }

    # assessment
    _ = assessment.nominal_bandwidth_hz
    with Clock() as warm:
        assessment(torch.as_tensor(train[:cs]))
    n = args.batches * cs
    walls, cpus = [], []
    for _ in range(args.repeat):
        healthy, wall, cpu = 0, 0.0, 0.0
        for b in range(1, args.batches + 1):
            with Clock() as c:
                res = assessment(torch.as_tensor(train[b * cs : (b + 1) * cs]))
            healthy += int(res.healthy.sum())
            wall, cpu = wall + c.wall, cpu + c.cpu
        walls.append(round(1000 * wall / n, 3))
        cpus.append(round(1000 * cpu / n, 3))
    out["assessment"] = {
        "vectors": n,
        "warmup_compile_wall_s": round(warm.wall, 2),
        "ms_per_vector_wall": statistics.median(walls),
        "ms_per_vector_cpu": statistics.median(cpus),
        "ms_per_vector_wall_runs": walls,
        "healthy_fraction": round(healthy / n, 4),
        "settling": assessment.settling(),
    }
    print(json.dumps(out["assessment"]), flush=True)

    # HF signals
    sim = EMASimulator(params, spec.fidelity, effects=spec.effects, substeps=spec.substeps, compile=spec.compile)
    k = torch.as_tensor(train[:cs])
    timings = []
    for _ in range(1 + args.repeat):
        with Clock() as c, torch.no_grad():
            sim.run(k, command, command.duration, channels=["current", "position"], out_dtype=torch.float32)
        timings.append(c)
    rates = [round(cs / t.wall, 2) for t in timings[1:]]
    out["signals"] = {
        "batch": cs,
        "warmup_compile_wall_s": round(timings[0].wall, 2),
        "signals_per_s_wall": statistics.median(rates),
        "signals_per_s_cpu": statistics.median(round(cs / t.cpu, 2) for t in timings[1:]),
        "signals_per_s_wall_runs": rates,
    }
    print(json.dumps(out["signals"]), flush=True)

    per_chunk_wall = cs / out["signals"]["signals_per_s_wall"] + cs * out["assessment"]["ms_per_vector_wall"] / 1000
    compile_wall = (
        out["signals"]["warmup_compile_wall_s"]
        - cs / out["signals"]["signals_per_s_wall"]
        + out["assessment"]["warmup_compile_wall_s"]
        - cs * out["assessment"]["ms_per_vector_wall"] / 1000
    )
    out["paper_extrapolated"] = {
        "note": "extrapolated from the batches above: compilations + chunks x "
        "(signals + assessment); merge and I/O not included",
        "wall_s": round(compile_wall + plan.n_chunks * per_chunk_wall, 1),
    }

    if args.full:
        with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
            full_cfg = compose(
                "generate", ["experiment=paper", *args.override, f"data_dir={args.full}", "progress=false"]
            )
        with Clock() as c:
            metrics, _ = generate(full_cfg)
        out["paper_full"] = {"wall_s": round(c.wall, 1), "cpu_s": round(c.cpu, 1), "metrics": metrics}
    out["machine"]["load_avg_end"] = os.getloadavg()
    with atomic_open(args.out, "w") as fh:
        json.dump(out, fh, indent=2)
        fh.write("\n")
    print(json.dumps(out, indent=2))


if __name__ == "__main__":
    main()
