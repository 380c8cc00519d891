"""The input contract's checks of runs in a full record: a gap of missing samples, a stuck value, held data; and
none of them on records that repeat values because of their resolution (noise-free or noisy, coarse ADC)."""

from __future__ import annotations

import math

import pytest
import torch

from phm_torch.online.run_checks import run_reasons

N = 10001


def _record(noise: float, seed: int = 0) -> torch.Tensor:
    """A chirp-like current (N,) [A], smooth, slow near its turning points, with relative white noise."""
    t = torch.linspace(0.0, 0.5, N, dtype=torch.float64)
    x = 0.9 * torch.sin(2 * math.pi * (1.0 + 15.0 * t) * t) * (1.0 - 0.3 * t) + 0.05
    g = torch.Generator().manual_seed(seed)
    return x + noise * 0.9 * torch.randn(N, generator=g, dtype=torch.float64)


@pytest.mark.parametrize("noise", [0.0, 0.01])
@pytest.mark.parametrize("resolution", [0.0, 1e-4, 1e-3, 1e-2, 3e-2])
def test_records_repeating_values_at_their_resolution_are_not_flagged(noise, resolution):
    x = _record(noise)
    if resolution:
        x = torch.round(x / resolution) * resolution
        assert float((x[1:] == x[:-1]).double().mean()) > (0.01 if noise == 0 else 0.0)  # it does repeat values
    assert run_reasons(x) == []
    lead = x.clone()
    lead[:400] = 0.0  # at rest before the trigger: a leading run
    assert run_reasons(lead) == []


def test_a_stuck_value_a_burst_of_zeros_a_gap_and_held_data_are_flagged():
    x = _record(0.01)
    stuck = x.clone()
    stuck[4000:4100] = stuck[3999]  # 1 % of the record at its last value
    zeros = x.clone()
    zeros[6000:6060] = 0.0
    gap = x.clone()
    gap[2000:2060] = float("nan")
    assert run_reasons(stuck) == ["stuck"] and run_reasons(zeros) == ["stuck"] and run_reasons(gap) == ["gap"]
    short = x.clone()
    short[2000:2040] = float("nan")  # 0.4 %: below the threshold
    short[5000:5040] = 0.0
    assert run_reasons(short) == []
    scattered = x.clone()
    scattered[::50] = float("nan")  # scattered missing samples are the pipeline's `missing` check
    assert run_reasons(scattered) == []
    for k in (2, 5, 20):
        held = x[(torch.arange(N) // k) * k]
        assert run_reasons(held) == ["held"], k


def test_a_short_record_needs_a_run_of_a_dozen_samples():
    """0.5 % of a 501-sample record (0.1 s at 5 kHz) is 2.5 samples: a clean record's runs of 3-4 equal samples
    would be `stuck`. The threshold is never below STUCK_MIN samples."""
    from phm_torch.online.run_checks import STUCK_MIN

    x = _record(0.01)[::20][:501]
    for run in (3, 4, STUCK_MIN - 1):  # equal samples
        short = x.clone()
        short[200 : 199 + run] = short[199]
        assert run_reasons(short) == [], run
        gap = x.clone()
        gap[300 : 300 + run] = float("nan")
        assert run_reasons(gap) == [], run
    stuck = x.clone()
    stuck[200 : 199 + STUCK_MIN] = stuck[199]
    assert run_reasons(stuck) == ["stuck"]
