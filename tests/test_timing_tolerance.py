"""The current's timing tolerance (phm_torch/online/timing_tolerance.py): its k intervals hold every reading within it,
so a current-only record a fraction of a millisecond late keeps the truth inside them, and so does a record whose
current channel alone lags its command column; a tolerance of 0 reads as before; a bad tolerance is refused by name."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import pytest
import torch

from phm_torch.faults import FAULT_NAMES
from phm_torch.online.corruptions import Record, delayed
from phm_torch.online.timing_tolerance import TIMING_TOLERANCE_S, tolerance_seconds, tolerance_shifts

RATE = 20000.0
PIPELINE = Path(__file__).resolve().parents[1] / "pretrained" / "online_surrogates_best.pt"
DAMAGE = [name for name in FAULT_NAMES if name != "eccentricity_phase"]


def test_the_tolerance_reads_the_timing_scans_grid_within_it():
    assert tolerance_shifts(10001, RATE, 5e-4) == list(range(-10, 11, 2))  # 0.5 ms: 10 samples, every second one
    assert tolerance_shifts(10001, RATE, 0.0) == [0]
    assert tolerance_shifts(1000, RATE, 1e-4) == [-2, -1, 0, 1, 2]  # a short record's grid: every sample


@pytest.mark.parametrize("bad", [-1e-4, float("nan"), float("inf"), True, "0.5 ms"])
def test_a_bad_tolerance_is_refused_by_name(bad):
    with pytest.raises(ValueError, match=r"timing_tolerance must be a number of seconds >= 0"):
        tolerance_seconds(bad)
    assert tolerance_seconds(None) == TIMING_TOLERANCE_S and tolerance_seconds(0) == 0.0


@pytest.fixture(scope="module")
def pretrained():
    from phm_torch.online.diagnosis import contract_for
    from phm_torch.online.export import read_metadata
    from phm_torch.online.loaded import TorchScriptPipeline

    torch.set_num_threads(1)
    module = torch.jit.load(str(PIPELINE))
    model = TorchScriptPipeline(module, read_metadata(PIPELINE))
    nominal = module.nominal_record.double()
    g = torch.Generator().manual_seed(3)
    noisy = nominal + 0.01 * float(nominal.pow(2).mean().sqrt()) * torch.randn(nominal.numel(), generator=g).double()
    return model, contract_for(model, model.metadata, None), noisy


def _bounds(out: dict) -> torch.Tensor:
    return torch.tensor([out["k_interval"][name] for name in DAMAGE], dtype=torch.float64)


@pytest.mark.torchscript  # the shipped TorchScript file
def test_a_record_half_a_millisecond_late_keeps_the_truth_inside_its_widened_intervals(pretrained):
    from phm_torch.online.diagnosis import diagnose

    model, contract, noisy = pretrained
    t = torch.arange(noisy.numel(), dtype=torch.float64) / RATE
    truth = torch.tensor(model.nominal.tolist(), dtype=torch.float64)[[FAULT_NAMES.index(n) for n in DAMAGE]]
    late = Record(t, None, None, delayed(noisy, 10))  # 0.5 ms late: below what the timing check can see
    exact = diagnose(model, late, contract, timing_tolerance_s=0.0)
    tolerant = diagnose(model, late, contract)  # phm-predict's default
    assert exact["timing_tolerance"] is None and not exact["out_of_distribution"]
    inside = lambda b: bool(((truth >= b[:, 0] - 1e-9) & (truth <= b[:, 1] + 1e-9)).all())
    assert not inside(_bounds(exact))  # read as if on time: a damage out of its interval, unflagged
    assert inside(_bounds(tolerant))  # the on-time reading is among the tolerance's
    assert tolerant["timing_tolerance"]["tolerance_s"] == TIMING_TOLERANCE_S
    assert tolerant["timing_tolerance"]["readings"] == 21  # 1 ms: every second sample within 20
    assert (_bounds(tolerant)[:, 0] <= _bounds(exact)[:, 0]).all() and (
        _bounds(tolerant)[:, 1] >= _bounds(exact)[:, 1]
    ).all()
    assert tolerant["k_hat"] == exact["k_hat"] and tolerant["healthy"] == exact["healthy"]  # the answer: on time
    # the reference's nominal record lies near its health boundary (gain drift): its verdict changes within 1 ms,
    # and the record says so
    assert not tolerant["timing_tolerance"]["verdict_stable"]
    assert any("verdict changes within the record's timing tolerance" in m for m in tolerant["messages"])


@pytest.mark.torchscript
def test_a_current_channel_lagging_its_command_column_is_read_within_the_tolerance(pretrained):
    from phm_torch.command import Chirp
    from phm_torch.online.diagnosis import contract_for, diagnose

    model, _, noisy = pretrained
    command = Chirp()
    contract = contract_for(model, model.metadata, command)
    t = torch.arange(noisy.numel(), dtype=torch.float64) / RATE
    truth = torch.tensor(model.nominal.tolist(), dtype=torch.float64)[[FAULT_NAMES.index(n) for n in DAMAGE]]
    lagging = Record(t, command(t), None, delayed(noisy, 10))  # the command on time, the current alone 0.5 ms late
    exact = diagnose(model, lagging, contract, timing_tolerance_s=0.0)
    tolerant = diagnose(model, lagging, contract)
    assert exact["trigger_offset_s"] in (None, 0.0)  # the command column is on time: nothing to align
    assert exact["timing_tolerance"] is None and not exact["out_of_distribution"]
    inside = lambda b: bool(((truth >= b[:, 0] - 1e-9) & (truth <= b[:, 1] + 1e-9)).all())
    assert not inside(_bounds(exact)) and inside(_bounds(tolerant))
    assert tolerant["timing_tolerance"]["readings"] == 21
    assert tolerant["k_hat"] == exact["k_hat"]
    assert any("current channel's own delay" in m for m in tolerant["messages"])
    assert not any("current-only record's trigger" in m for m in tolerant["messages"])


@pytest.mark.torchscript
def test_a_best_shift_beyond_the_tolerance_below_refusal_widens_the_intervals_to_its_reading(pretrained):
    from phm_torch.online.diagnosis import contract_for, diagnose

    model, _, noisy = pretrained
    t = torch.arange(noisy.numel(), dtype=torch.float64) / RATE
    truth = torch.tensor(model.nominal.tolist(), dtype=torch.float64)[[FAULT_NAMES.index(n) for n in DAMAGE]]
    late = Record(t, None, None, delayed(noisy, 30))  # 1.5 ms late: beyond the tolerance
    # a pipeline whose clean records reach a ratio of 2 (its threshold): the record is not refused
    contract = contract_for(model, {**model.metadata, "timing_ratio_max": 2.0}, None)
    plain = diagnose(model, late, dataclasses.replace(contract, timing_ratio=None))  # no scan: the tolerance alone
    widened = diagnose(model, late, contract)
    assert not plain["out_of_distribution"] and not widened["out_of_distribution"]
    scan = widened["timing_check"]
    assert scan["ratio"] < 2.0 and scan["best_shift_s"] > TIMING_TOLERANCE_S
    assert plain["timing_tolerance"]["widened_to_s"] is None and plain["timing_tolerance"]["readings"] == 21
    assert widened["timing_tolerance"]["widened_to_s"] == pytest.approx(scan["best_shift_s"])
    assert widened["timing_tolerance"]["readings"] > 21
    inside = lambda b: bool(((truth >= b[:, 0] - 1e-9) & (truth <= b[:, 1] + 1e-9)).all())
    assert not inside(_bounds(plain)) and inside(_bounds(widened))  # the on-time reading is the best shift's
    assert widened["k_hat"] == plain["k_hat"]  # the answer stays the reading as it came
    assert any("explained best read as if 1.50 ms late" in m for m in widened["messages"])
