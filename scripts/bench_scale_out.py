"""Benchmark of phm-generate scale-out: the same small store by 1 and by 2 local workers; writes JSON.

Each run is the whole command, as a user types it (``python -m phm_torch.apps.generate -m
hydra/launcher=<launcher> shard.count=<w> 'shard.index=range(<w>)'``), into a fresh data_dir, plus a
``stage=merge`` run when no shard saw every chunk at its end. ``none`` is the plain single-process command
(no launcher, no ``-m``): the baseline the launchers' start-up cost shows against. Every run's manifest must
equal the first one's (the same data, whatever the sharding), else the script stops.

The wall time includes the launcher's start (a local Ray instance: ~10 s; submitit: a Python process per
job) and each shard's imports; on a shared machine it also includes the waits for other processes, so
the load average is recorded before and after each run, and the machine's own speed-up from 1 to the
largest worker count (a CPU-bound loop in that many processes side by side against one alone) before and
after all runs: the ceiling of any launcher's speed-up at the time. ``shard_compute_s``: each shard's own
wall time (its chunks and the merge, without start-up), from the metrics it prints. Ray gets ``num_cpus``
= the largest worker count for every run and each shard reserves one CPU (``threads=1``).

Usage: python scripts/bench_scale_out.py [--launchers none ray_cluster submitit_local] [--workers 1 2]
       [--repeats 1] [--out scripts/bench_scale_out.json]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import re
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import torch

from phm_torch.io.atomic import atomic_open

APP = "phm_torch.apps.generate"
# LF signals of a 0.1 s command, 152 rows in 8 chunks of 19 (4 per shard with 2 workers), 5 test frequencies
SMALL = (
    "dataset.fidelity=lf",
    "command.duration=0.1",
    "dataset.n_train=136",
    "dataset.n_val=10",
    "dataset.n_rul=5",
    "dataset.chunk_size=19",
    "dataset.n_labels=0",
    "+dataset.healthy_fraction=null",
    "assessment.sweep.frequencies=[15,30,60,90,130]",
    "assessment.sweep.cycles=3",
    "assessment.sweep.group_size=5",
    "progress=false",
    "threads=1",
)
LAUNCHERS = ("none", "ray_cluster", "submitit_local", "local")


def command(launcher: str, workers: int, run_dir: Path, max_workers: int) -> list[str]:
    """The phm-generate command line of one run (``none``: one plain process, ``workers`` must be 1)."""
    data = [*SMALL, f"data_dir={run_dir / 'store'}"]
    if launcher == "none":
        return [sys.executable, "-m", APP, *data, f"hydra.run.dir={run_dir / 'hydra'}"]
    extra = {
        "ray_cluster": [f"+hydra.launcher.ray.init.num_cpus={max_workers}"],
        "local": [f"hydra.launcher.n_jobs={workers}"],
    }.get(launcher, [])
    shards = [f"shard.count={workers}", f"shard.index=range({workers})"]
    sweep = [f"hydra/launcher={launcher}", f"hydra.sweep.dir={run_dir / 'multirun'}", *extra]
    return [sys.executable, "-m", APP, "-m", *data, *shards, *sweep]  # -m (multirun) before the overrides


def run(cmd: list[str], cwd: Path) -> tuple[float, str]:
    """Wall time [s] and stdout of ``cmd``; raises with its stderr's tail when it fails."""
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    t0 = time.perf_counter()
    proc = subprocess.run(cmd, cwd=cwd, env=env, capture_output=True, text=True, check=False)
    wall = time.perf_counter() - t0
    if proc.returncode != 0:
        raise RuntimeError(f"{' '.join(cmd)} failed ({proc.returncode}):\n{proc.stderr[-3000:]}")
    return wall, proc.stdout


def one(launcher: str, workers: int, root: Path, max_workers: int) -> dict[str, Any]:
    run_dir = root / f"{launcher}_{workers}_{len(list(root.iterdir()))}"
    load = os.getloadavg()
    wall, stdout = run(command(launcher, workers, run_dir, max_workers), root)
    # each shard prints its metrics: Ray forwards them to the driver's stdout, submitit to its job logs
    logs = [stdout, *(f.read_text() for f in sorted(run_dir.glob("multirun/.submitit/*/*_log.out")))]
    shard_s = [float(x) for text in logs for x in re.findall(r'"wall_time_s": ([0-9.]+)', text)]
    merge_s = 0.0
    if not (run_dir / "store" / "manifest.json").exists():  # every shard finished before the others' chunks
        merge_s, _ = run(
            [
                sys.executable,
                "-m",
                APP,
                *SMALL,
                f"data_dir={run_dir / 'store'}",
                "stage=merge",
                f"hydra.run.dir={run_dir / 'merge'}",
            ],
            root,
        )
    manifest = json.loads((run_dir / "store" / "manifest.json").read_text())
    return {
        "launcher": launcher,
        "workers": workers,
        "wall_s": round(wall + merge_s, 2),
        "merge_s": round(merge_s, 2),
        "shard_compute_s": shard_s,  # each shard's own wall time (chunks + merge), without start-up
        "load_avg_before": [round(x, 2) for x in load],
        "load_avg_after": [round(x, 2) for x in os.getloadavg()],
        "manifest": manifest,
    }


SPIN = "s = 0\nfor i in range(15_000_000):\n    s += i"  # a pure-Python loop, ~1 s of one core


def machine_parallelism(workers: int) -> float:
    """The machine's own speed-up from 1 to ``workers`` processes right now: ``workers`` copies of a CPU-bound
    loop side by side against one alone (2.0 on two idle cores; ~1 when other jobs already fill them)."""

    def wall(n: int) -> float:
        t0 = time.perf_counter()
        procs = [subprocess.Popen([sys.executable, "-c", SPIN]) for _ in range(n)]
        for proc in procs:
            proc.wait()
        return time.perf_counter() - t0

    return round(workers * wall(1) / wall(workers), 2)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--launchers", nargs="+", default=["none", "ray_cluster", "submitit_local"], choices=LAUNCHERS)
    ap.add_argument("--workers", nargs="+", type=int, default=[1, 2])
    ap.add_argument("--repeats", type=int, default=1, help="runs per (launcher, workers), alternating the order")
    ap.add_argument("--out", default=str(Path(__file__).with_suffix(".json")))
    args = ap.parse_args()
    if any(w < 1 for w in args.workers):
        raise SystemExit(f"--workers must be >= 1, got {args.workers}")
    max_workers = max(args.workers)
    runs: list[dict[str, Any]] = []
    reference = None
    control = {"before": machine_parallelism(max_workers)}
    with tempfile.TemporaryDirectory(prefix="bench_scale_out_") as tmp:
        root = Path(tmp)
        for r in range(args.repeats):
            for launcher in args.launchers:
                counts = [1] if launcher == "none" else args.workers
                for w in counts if r % 2 == 0 else counts[::-1]:
                    res = one(launcher, w, root, max_workers)
                    manifest = res.pop("manifest")
                    reference = reference or manifest
                    if manifest != reference:
                        raise SystemExit(f"{launcher} with {w} workers wrote another manifest than the first run")
                    runs.append(res)
                    print(json.dumps(res), flush=True)
    control["after"] = machine_parallelism(max_workers)
    speedup = {}
    for launcher in args.launchers:
        walls = {
            w: min(x["wall_s"] for x in runs if x["launcher"] == launcher and x["workers"] == w)
            for w in ({1} if launcher == "none" else set(args.workers))
        }
        if 1 in walls and max_workers in walls and max_workers > 1:
            speedup[launcher] = round(walls[1] / walls[max_workers], 2)
    out = {
        "machine": {
            "cpus": os.cpu_count(),
            "platform": platform.platform(),
            "torch": torch.__version__,
            "python": platform.python_version(),
            "note": "shared machine: other processes run beside these; see each run's load average",
        },
        "config": {
            "overrides": list(SMALL),
            "signals": sum(v["count"] for v in reference["splits"].values()),
            "chunks": reference["n_chunks"],
            "fingerprint": reference["fingerprint"],
        },
        "runs": runs,
        "speedup_1_to_max_workers": speedup,
        "machine_speedup_1_to_max_workers": control,  # the ceiling: the same processes count on a CPU-bound loop
        "note": "wall_s: the whole command (launcher start, imports, shards, merge); best of the repeats",
    }
    with atomic_open(args.out, "w") as fh:
        json.dump(out, fh, indent=2)
        fh.write("\n")
    print(json.dumps({"speedup_1_to_max_workers": speedup, "machine_speedup_1_to_max_workers": control}), flush=True)


if __name__ == "__main__":
    main()
