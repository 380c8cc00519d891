"""Online latency and throughput of an exported pipeline (TorchScript), one thread; writes JSON.

Measures, on signals of the store's ``rul`` split (or the model's mean signal when no store is given):
FDI (selected samples -> gappy POD -> MLP -> k_hat) p50/p99 for one signal, the full online step
(k_hat, health score, RUL 5/50/95, OOD flag) p50/p99 for one signal, and batched throughput.

Usage: python scripts/bench_online.py --model results/evaluate/online.pt [--data-dir DIR] [--out results/bench_online.json]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import time
from pathlib import Path

import torch

from phm_torch.timing import call_times_us, percentiles_us


def percentiles(fn, repeats: int) -> dict[str, float]:
    return percentiles_us(call_times_us(fn, repeats))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--model", required=True)
    ap.add_argument("--data-dir", default=None)
    ap.add_argument("--repeats", type=int, default=2000)
    ap.add_argument("--batch", type=int, default=4096)
    ap.add_argument("--out", default="results/bench_online.json")
    args = ap.parse_args()
    torch.set_num_threads(1)
    model = torch.jit.load(args.model).eval()
    dtype = model.times.dtype
    if args.data_dir:
        import h5py

        with h5py.File(Path(args.data_dir) / "dataset.h5", "r") as f:
            signals = torch.as_tensor(f["rul"]["current"][:64], dtype=dtype)
    else:
        signals = model.gappy.mean_hat.new_zeros(1, model.n_full) + float(model.gappy.mean_hat.mean())
    one = signals[:1]
    samples = one.index_select(1, model.gappy.indices)
    with torch.no_grad():
        def fdi():
            alpha, _ = model.gappy(samples, None)
            return model.fdi(alpha)

        report = {"fdi_samples_to_k": percentiles(fdi, args.repeats),
                  "online_step_full_signal": percentiles(lambda: model(one), args.repeats // 4),
                  "online_step_selected_samples": percentiles(lambda: model(samples), args.repeats // 4)}
        batch = signals[torch.arange(args.batch) % signals.shape[0]].contiguous()
        model(batch[:256])
        t0 = time.perf_counter()
        model(batch)
        report["batched_signals_per_s"] = args.batch / (time.perf_counter() - t0)
    report["machine"] = {"platform": platform.platform(), "cpus": os.cpu_count(), "threads": 1}
    report["targets"] = {"fdi_p50_us": 100, "online_step_p50_us": 1000, "batched_signals_per_s": 10000}
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = out.with_suffix(".tmp")
    tmp.write_text(json.dumps(report, indent=2))
    os.replace(tmp, out)
    print(json.dumps(report, indent=2))


if __name__ == "__main__":
    main()
