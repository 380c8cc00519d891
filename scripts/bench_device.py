"""The accelerator paths side by side with the CPU of the same machine: simulation and the online step; writes JSON.

What runs on a GPU in this project, measured on ``--device`` (e.g. ``cuda``) and, as the baseline, on that machine's
CPU with every core (``--cpu-threads``, default all):

* ``simulate``: signals/s of the HF and LF simulators on the paper's test chirp (``--duration`` seconds of it, the
  rate scaled to whole 0.5 s chirps: the time-stepping loop costs the same per step over the whole chirp) at each
  ``--sim-batch``, eager and (``--compile``) ``torch.compile``-d, the signals kept in float32 as generation keeps
  them; the compile's one-off cost is reported apart;
* ``online``: the whole online step (:class:`~phm_torch.online.step.OnlineStep`, every output phm-predict reads) of
  a pipeline file, rebuilt eager from its TorchScript (:func:`~phm_torch.online.from_torchscript.pipeline_from_torchscript`)
  and moved to the device: records/s at each ``--online-batch`` and the p50/p99 latency of one record, with the
  device synchronised around every timed call; and the largest difference of its outputs from the CPU's on the same
  64 records (k_hat, RUL), so a figure never hides a wrong answer.

Generation and training through the apps on a device are ``phm-generate device=cuda`` and
``phm-train trainer.accelerator=gpu`` (docs/scale_out.md gives the figures of one run).

Usage: python scripts/bench_device.py --device cuda [--pipeline pretrained/online_surrogates_best.pt]
[--compile] [--out results/bench_device.json]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import time
import traceback
from collections.abc import Callable
from pathlib import Path

import torch

from phm_torch.io.atomic import atomic_open

CHIRP_S = 0.5  # the paper's test chirp: rates are per whole chirp


def _sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def _timed(fn: Callable[[], object], device: torch.device) -> float:
    _sync(device)
    t0 = time.perf_counter()
    fn()
    _sync(device)
    return time.perf_counter() - t0


def bench_simulate(
    device: torch.device, fidelity: str, batch: int, duration: float, compile: bool, repeats: int
) -> dict:
    """Signals per second (whole chirps) of one simulator configuration."""
    from phm_torch.command import Chirp
    from phm_torch.params import load_actuator
    from phm_torch.simulator import EMASimulator

    k = torch.rand(batch, 8, generator=torch.Generator().manual_seed(0), dtype=torch.float64) ** 8
    sim = EMASimulator(load_actuator(), fidelity, compile=compile, device=device)
    cmd = Chirp(duration=CHIRP_S)
    kw = {"channels": ["current", "position"], "out_dtype": torch.float32}

    def run(d: float) -> None:
        for _ in sim.iter_chunks(k, cmd, d, batch, **kw):
            pass

    warmup = _timed(lambda: run(min(duration, 0.002)), device)  # the compile, or the first kernels' load
    times = [_timed(lambda: run(duration), device) for _ in range(repeats)]
    med = statistics.median(times)
    return {
        "fidelity": fidelity,
        "batch": batch,
        "compile": compile,
        "duration_s": duration,
        "wall_s": times,
        "signals_per_s": batch * duration / CHIRP_S / med,
        "warmup_s": warmup,
        "peak_gpu_gb": torch.cuda.max_memory_allocated(device) / 1e9 if device.type == "cuda" else None,
    }


def _records(pipeline, n: int) -> torch.Tensor:
    base = pipeline.nominal_record
    g = torch.Generator().manual_seed(0)
    noise = 0.01 * base.abs().mean() * torch.randn(n, base.shape[0], generator=g, dtype=base.dtype)
    return (base + noise).contiguous()


def bench_online(
    step, records: torch.Tensor, device: torch.device, batches: list[int], repeats: int, work: int
) -> dict:
    """Records/s at each batch (``work`` records a timed repetition) and one record's latency of an OnlineStep
    already on ``device``."""
    offset = torch.zeros(records.shape[1], dtype=records.dtype, device=device)
    out: dict = {}
    with torch.no_grad():
        one = records[:1].to(device)
        for _ in range(20):
            step(one, offset)
        lat = sorted(_timed(lambda: step(one, offset), device) * 1e6 for _ in range(repeats))
        out["one_record_us"] = {"p50": lat[len(lat) // 2], "p99": lat[int(0.99 * (len(lat) - 1))]}
        for n in batches:
            x = records[torch.arange(n) % records.shape[0]].to(device)
            step(x, offset)  # warm-up at this size
            calls = max(1, work // n)
            times = [_timed(lambda x=x, c=calls: [step(x, offset) for _ in range(c)], device) for _ in range(3)]
            out[f"records_per_s_{n}"] = calls * n / statistics.median(times)
    return out


def online_section(args: argparse.Namespace, device: torch.device) -> dict:
    from phm_torch.online.from_torchscript import pipeline_from_torchscript
    from phm_torch.online.step import OnlineStep

    pipeline, _ = pipeline_from_torchscript(args.pipeline)
    records = _records(pipeline, 64)
    cpu_step = OnlineStep(pipeline, full=True).eval()
    offset = torch.zeros(records.shape[1], dtype=records.dtype)
    with torch.no_grad():
        ref = cpu_step(records, offset)
    dev_step = OnlineStep(pipeline_from_torchscript(args.pipeline)[0], full=True).eval().to(device)
    with torch.no_grad():
        got = [t.cpu() for t in dev_step(records.to(device), offset.to(device))]
    diff = {}
    for name, i in (("k_hat", 0), ("rul", 5)):
        a, b = ref[i].double(), got[i].double()
        diff[name] = float(((a - b).abs() / a.abs().clamp_min(1e-6)).nan_to_num(0.0).max())
    res = {"file": args.pipeline, "dtype": str(records.dtype), "max_rel_diff_vs_cpu": diff}
    res[device.type] = bench_online(dev_step, records, device, args.online_batch, args.repeats, args.work)
    torch.set_num_threads(args.cpu_threads)
    cpu_batches = [n for n in args.online_batch if n <= 4096]  # the CPU's best sizes (docs/prognostics.md)
    res[f"cpu@{args.cpu_threads}"] = bench_online(
        cpu_step, records, torch.device("cpu"), cpu_batches, args.repeats, args.work
    )
    return res


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--device", default="cuda")
    ap.add_argument("--pipeline", default="pretrained/online_surrogates_best.pt")
    ap.add_argument("--duration", type=float, default=0.05, help="seconds of the chirp simulated per timed run")
    ap.add_argument("--sim-batch", type=int, action="append", help="simulator batches (default 1024, 16384)")
    ap.add_argument("--online-batch", type=int, action="append", help="online batches (default 256, 4096, 65536)")
    ap.add_argument("--compile", action="store_true", help="also the torch.compile-d simulators")
    ap.add_argument("--cpu-threads", type=int, default=os.cpu_count())
    ap.add_argument("--cpu-sim-batch", type=int, default=1024, help="the CPU baseline's simulator batch")
    ap.add_argument("--work", type=int, default=65536, help="records per timed repetition of a batched rate")
    ap.add_argument("--repeats", type=int, default=200, help="timed one-record calls")
    ap.add_argument("--skip", action="append", default=[], choices=["simulate", "online"])
    ap.add_argument("--out", default="results/bench_device.json")
    args = ap.parse_args()
    args.sim_batch = args.sim_batch or [1024, 16384]
    args.online_batch = args.online_batch or [256, 4096, 65536]
    if args.duration <= 0 or args.duration > CHIRP_S:
        ap.error(f"--duration must be in (0, {CHIRP_S}], got {args.duration}")
    device = torch.device(args.device)
    report: dict = {
        "machine": {
            "platform": platform.platform(),
            "cpus": os.cpu_count(),
            "torch": torch.__version__,
            "device": torch.cuda.get_device_name(device) if device.type == "cuda" else str(device),
            "cpu_threads": args.cpu_threads,
        }
    }

    def save() -> None:
        Path(args.out).parent.mkdir(parents=True, exist_ok=True)
        with atomic_open(Path(args.out), "w") as fh:
            fh.write(json.dumps(report, indent=2))

    def section(name: str, fn: Callable[[], object]) -> None:
        t0 = time.perf_counter()
        try:
            report[name] = fn()
        except Exception:  # noqa: BLE001 (reported in the JSON) one failing section must not lose the others' figures
            report[name] = {"error": traceback.format_exc()}
        print(f"[{name}] {time.perf_counter() - t0:.1f} s: {json.dumps(report[name])[:600]}", flush=True)
        save()

    if "online" not in args.skip:
        section("online", lambda: online_section(args, device))
    if "simulate" not in args.skip:
        for fidelity in ("hf", "lf"):
            for batch in args.sim_batch:
                section(
                    f"simulate_{fidelity}_{batch}",
                    lambda f=fidelity, b=batch: bench_simulate(device, f, b, args.duration, False, 2),
                )
        torch.set_num_threads(args.cpu_threads)
        for fidelity in ("hf", "lf"):
            section(
                f"simulate_{fidelity}_{args.cpu_sim_batch}_cpu@{args.cpu_threads}",
                lambda f=fidelity: bench_simulate(torch.device("cpu"), f, args.cpu_sim_batch, args.duration, False, 2),
            )
        batch = max(args.sim_batch)  # compiled last and at one size: each shape is a compile of its own
        for fidelity in ("hf", "lf") if args.compile else ():
            section(
                f"simulate_{fidelity}_{batch}_compiled",
                lambda f=fidelity: bench_simulate(device, f, batch, args.duration, True, 2),
            )
    save()


if __name__ == "__main__":
    main()
