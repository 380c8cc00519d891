"""Online latency and throughput of exported pipelines, every format side by side; writes JSON.

Each ``--model`` file (TorchScript ``.pt``, torch.export ``.pt2``, AOTInductor ``.aoti.pt2``, ONNX ``.onnx.zip``
run with ONNX Runtime at the same thread count, ExecuTorch ``.pte.zip``; the same pipeline
exported by ``phm-export format=[...]``) is loaded with :func:`phm_torch.online.loaded.load_pipeline` and timed on
the same records (the store's ``rul`` split with ``--data-dir``, else the pipeline's nominal record), in
alternating order (round-robin over the formats, ``--rounds`` rounds, medians over all of them):

* ``step_full`` p50/p99: one full record through everything phm-predict reads (k_hat, intervals at the measured
  noise, score, P(faulty), RUL 5/50/95, OOD flag and reasons, residual, noise): the TorchScript file's forward +
  methods (:meth:`TorchScriptPipeline.run`), one program call for the others;
* ``forward_full`` p50/p99 (TorchScript only): its ``forward`` alone, the figure this script reported before;
* ``step_samples`` p50/p99: one record of selected samples;
* ``fdi`` p50/p99 (TorchScript, and aoti packages with their FDI program): selected samples -> gappy POD -> MLP
  -> k_hat, one call of ``k_hat_of_samples`` (the gappy least squares folded into the first layer; older
  TorchScript files: the two submodules);
* ``records_per_s_256`` / ``records_per_s_4096``: batched throughput of the full step, 4,096 records per round at
  either size (16 calls of 256, one of 4,096; a program format's loader calls its program on at most 256 records
  at a time, :data:`~phm_torch.online.loaded.CALL_BATCH`), on one thread;
* ``records_per_s_by_threads``: the same two throughputs at each ``--threads`` count (intra-op threads, every
  format at the same count within a round, each from a copy loaded at that count: a batch is what a ground server
  runs on every core it has; ExecuTorch's portable kernels run on one thread whatever the count);
* ``load_s`` (median of 3 loads) and ``file_bytes``.

Latencies are on one thread. Usage: python scripts/bench_online.py --model a.pt --model a.pt2 [--data-dir DIR]
[--threads 1 --threads 2] [--out results/bench_online.json]
(two files of one format, e.g. two builds of a package, are reported under "<format> <path>" for the second)
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import time
from pathlib import Path

import torch

from phm_torch.io.atomic import atomic_open
from phm_torch.online.loaded import load_pipeline
from phm_torch.timing import call_times_us, percentiles_us

TARGETS = {"step_full_p50_us": 500, "records_per_s": 20000, "fdi_p50_us": 50, "torchscript_records_per_s": 10000}


def _records(model, data_dir: str | None) -> torch.Tensor:
    if data_dir:
        import h5py

        with h5py.File(Path(data_dir) / "dataset.h5", "r") as f:
            return torch.as_tensor(f["rul"]["current"][:64], dtype=model.dtype)
    base = model.nominal_record if model.nominal_record is not None else torch.ones(model.n_full, dtype=model.dtype)
    noise = 0.01 * base.abs().mean() * torch.randn(64, model.n_full, generator=torch.Generator().manual_seed(0))
    return (base + noise.to(model.dtype)).contiguous()


def _throughput(model, batch: torch.Tensor) -> float:
    """Records per second of the full step on 4,096 records in calls of ``batch``'s size."""
    model.run(batch[:64])
    calls = max(1, 4096 // batch.shape[0])  # the same 4,096 records of work at either size: steady state, not
    t0 = time.perf_counter()  # one cold call after another format ran (its caches are the others')
    for _ in range(calls):
        model.run(batch)
    return calls * batch.shape[0] / (time.perf_counter() - t0)


def _load(path: str) -> tuple[object, float]:
    times = []
    for _ in range(3):
        t0 = time.perf_counter()
        model = load_pipeline(path)
        times.append(time.perf_counter() - t0)
    return model, statistics.median(times)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--model", action="append", required=True, help="a pipeline file; repeat for each format")
    ap.add_argument("--data-dir", default=None)
    ap.add_argument("--repeats", type=int, default=200, help="timed single-record calls per format and round")
    ap.add_argument("--rounds", type=int, default=5)
    ap.add_argument(
        "--threads",
        type=int,
        action="append",
        default=None,
        help="intra-op threads of the batched throughput; repeat for several (default: 1 and every core)",
    )
    ap.add_argument("--out", default="results/bench_online.json")
    args = ap.parse_args()
    thread_counts = sorted(set(args.threads or [1, os.cpu_count() or 1]))
    if any(n < 1 for n in thread_counts):
        ap.error(f"--threads must be >= 1, got {thread_counts}")
    torch.set_num_threads(1)
    models, report = {}, {}
    for path in args.model:
        model, load_s = _load(path)
        key = model.format if model.format not in models else f"{model.format} {path}"  # two builds side by side
        models[key] = model
        report[key] = {"file": path, "file_bytes": os.path.getsize(path), "load_s": load_s}
    # a copy of each loaded at every other thread count: ONNX Runtime fixes a session's threads when it is made
    # (onnx_format.py: torch's count at load), the torch formats read torch's count at each call
    threaded = {1: models}
    for threads in thread_counts:
        if threads != 1:
            torch.set_num_threads(threads)
            threaded[threads] = {key: load_pipeline(report[key]["file"]) for key in models}
    torch.set_num_threads(1)
    first = next(iter(models.values()))
    signals = _records(first, args.data_dir)
    one = signals[:1]
    indices = first.gappy.indices if first.format == "torchscript" else first.indices  # the selected samples
    samples = one.index_select(1, indices)
    batches = {n: signals[torch.arange(n) % signals.shape[0]].contiguous() for n in (256, 4096)}
    times: dict[str, dict[str, list[float]]] = {fmt: {} for fmt in models}
    with torch.no_grad():
        for _ in range(args.rounds):  # round-robin: a slow spell of the shared machine hits every format
            for fmt, model in models.items():
                t = times[fmt]
                t.setdefault("step_full", []).extend(call_times_us(lambda m=model: m.run(one), args.repeats))
                t.setdefault("step_samples", []).extend(call_times_us(lambda m=model: m.run(samples), args.repeats))
                if model.format == "torchscript":
                    m = model.module
                    t.setdefault("forward_full", []).extend(call_times_us(lambda m=m: m(one), args.repeats))

                    def fdi(m=m):
                        if hasattr(m, "k_hat_of_samples"):  # the FDI alone, folded (online/sample_fdi.py)
                            return m.k_hat_of_samples(samples)
                        alpha, _ = m.gappy(samples, None)  # a pipeline exported before it: the two layers
                        return m.fdi(alpha)

                    t.setdefault("fdi", []).extend(call_times_us(fdi, args.repeats))
                elif getattr(model, "fdi_program", None) is not None:  # an aoti package's FDI program, called alone
                    t.setdefault("fdi", []).extend(call_times_us(lambda m=model: m.fdi_program(samples), args.repeats))
                for threads in thread_counts:
                    torch.set_num_threads(threads)
                    for n, batch in batches.items():
                        rate = _throughput(threaded[threads][fmt], batch)
                        t.setdefault(f"records_per_s_{n}@{threads}", []).append(rate)
                torch.set_num_threads(1)
    for fmt, t in times.items():
        by_threads: dict[str, dict[str, float]] = {}
        for key, values in t.items():
            if key.startswith("records"):
                name, threads = key.split("@")
                by_threads.setdefault(threads, {})[name] = statistics.median(values)
            else:
                report[fmt][key] = percentiles_us(sorted(values))
        report[fmt].update(by_threads.get("1", {}))  # the one-thread figures where earlier reports had them
        report[fmt]["records_per_s_by_threads"] = by_threads
    report["machine"] = {
        "platform": platform.platform(),
        "cpus": os.cpu_count(),
        "threads": 1,
        "throughput_threads": thread_counts,
        "torch": torch.__version__,
        "note": "shared machine: medians over alternating rounds; latencies on one thread",
    }
    report["targets"] = TARGETS
    out = Path(args.out)
    with atomic_open(out, "w") as fh:
        fh.write(json.dumps(report, indent=2))
    print(json.dumps(report, indent=2))


if __name__ == "__main__":
    main()
