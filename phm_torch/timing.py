"""Wall-clock latency of a callable: the one timing loop behind every latency figure of phm_torch."""

from __future__ import annotations

import os
import statistics
import time
from collections.abc import Callable
from typing import Any

import torch


def call_times_us(fn: Callable[[], Any], repeats: int, warmup: int = 20) -> list[float]:
    """Sorted wall times [us] of ``repeats`` calls of ``fn()``, after ``warmup`` untimed calls."""
    if repeats < 1:
        raise ValueError(f"repeats must be >= 1, got {repeats}")
    for _ in range(warmup):
        fn()
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter_ns()
        fn()
        times.append((time.perf_counter_ns() - t0) / 1e3)
    return sorted(times)


def percentiles_us(times: list[float]) -> dict[str, float]:
    """p50 and p99 [us] of sorted call times [us]."""
    return {"p50_us": statistics.median(times), "p99_us": times[int(0.99 * (len(times) - 1))]}


def torchscript_step_latency(model_path: str | os.PathLike, signals: torch.Tensor, repeats: int) -> dict[str, float]:
    """p50/p99 [us] of a TorchScript pipeline file's step on one signal of ``signals`` (B, n) (one thread), and its
    throughput [signals/s] on a batch of 1,024 copies: the ``phm-run`` report's latency table."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        model = torch.jit.load(str(model_path))
        one = signals[:1].to(model.times.dtype)
        with torch.no_grad():
            step = percentiles_us(call_times_us(lambda: model(one), repeats))
            batch = signals[:1].expand(1024, -1).to(model.times.dtype).contiguous()
            t0 = time.perf_counter()
            model(batch)
            throughput = 1024 / (time.perf_counter() - t0)
    finally:
        torch.set_num_threads(threads)
    return {
        "online_step_us_p50": step["p50_us"],
        "online_step_us_p99": step["p99_us"],
        "online_batched_signals_per_s": throughput,
    }
