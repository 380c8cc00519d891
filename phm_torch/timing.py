"""Wall-clock latency of a callable: the one timing loop behind every latency figure of phm_torch."""

from __future__ import annotations

import statistics
import time
from collections.abc import Callable
from typing import Any


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
