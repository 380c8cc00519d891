"""Online latency and throughput of exported pipelines, every format side by side, one thread; writes JSON.

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
  at a time, :data:`~phm_torch.online.loaded.CALL_BATCH`);
* ``load_s`` (median of 3 loads) and ``file_bytes``.

Usage: python scripts/bench_online.py --model a.pt --model a.pt2 [--data-dir DIR] [--out results/bench_online.json]
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
    ap.add_argument("--out", default="results/bench_online.json")
    args = ap.parse_args()
    torch.set_num_threads(1)
    models, report = {}, {}
    for path in args.model:
        model, load_s = _load(path)
        key = model.format if model.format not in models else f"{model.format} {path}"  # two builds side by side
        models[key] = model
        report[key] = {"file": path, "file_bytes": os.path.getsize(path), "load_s": load_s}
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
                for n, batch in batches.items():
                    model.run(batch[:64])
                    calls = max(1, 4096 // n)  # the same 4,096 records of work at either size: steady state, not
                    t0 = time.perf_counter()  # one cold call after another format ran (its caches are the others')
                    for _ in range(calls):
                        model.run(batch)
                    t.setdefault(f"records_per_s_{n}", []).append(calls * n / (time.perf_counter() - t0))
    for fmt, t in times.items():
        for key, values in t.items():
            report[fmt][key] = (
                statistics.median(values) if key.startswith("records") else percentiles_us(sorted(values))
            )
    report["machine"] = {
        "platform": platform.platform(),
        "cpus": os.cpu_count(),
        "threads": 1,
        "torch": torch.__version__,
        "note": "shared machine: medians over alternating rounds",
    }
    report["targets"] = TARGETS
    out = Path(args.out)
    with atomic_open(out, "w") as fh:
        fh.write(json.dumps(report, indent=2))
    print(json.dumps(report, indent=2))


if __name__ == "__main__":
    main()
