"""The timing check (phm_torch/online/timing_check.py): a current on time is explained best where it is; delayed or
advanced by a few milliseconds, the pipeline's own answer explains it best moved back by that much, and phm-predict
refuses it with the reason ``timing`` and the shift it found; the scan's grid, its decision and its calibration."""

from __future__ import annotations

import math
from pathlib import Path

import pytest
import torch

from phm_torch.online.corruptions import Record, delayed
from phm_torch.online.export import read_metadata
from phm_torch.online.input_contract import InputContract
from phm_torch.online.timing_check import (
    TIMING_RATIO,
    TimingScan,
    around,
    calibrate_timing_ratio,
    scan_shifts,
    timing_scan,
)

RATE = 20000.0
PIPELINE = Path(__file__).resolve().parents[1] / "pretrained" / "online_surrogates_best.pt"


def test_the_scan_reads_every_other_sample_within_a_fortieth_of_the_record():
    shifts = scan_shifts(10001)
    assert shifts[0] == -250 and shifts[-1] == 250 and 0 in shifts and set(map(abs, shifts)) <= set(range(0, 251, 2))
    assert scan_shifts(1000) == list(range(-25, 26))  # a short record: every sample


class _Landscape:
    """A pipeline stand-in whose consistency statistic is a known function of the shift it reads (the record is
    arange(n), so the shifted copy's middle sample names its shift); counts the shifted records read."""

    has_consistency, n_full, times = True, 10001, torch.zeros(1, dtype=torch.float64)

    def __init__(self, statistic):
        self.statistic, self.read = statistic, []

    def consistency(self, block, noise=None):
        shifts = (block[:, 5000] - 5000).round().long().tolist()
        self.read += shifts
        return torch.tensor([self.statistic(s) for s in shifts], dtype=torch.float64)


@pytest.mark.parametrize("true_shift", [-247, -101, -3, 0, 37, 94, 250])
def test_the_coarse_to_fine_scan_finds_the_step_by_step_minimum_with_a_third_of_the_reads(true_shift):
    # a bowl a few samples wide around the record's true shift, on a floor of ripples (the answer's own jitter)
    def bowl(s):
        return 1.0 + 0.2 * math.sin(0.7 * s) ** 2 - 0.6 / (1.0 + ((s - true_shift) / 6.0) ** 2)

    model = _Landscape(bowl)
    scan = timing_scan(model, torch.arange(10001, dtype=torch.float64), 0.01)
    grid = scan_shifts(10001)
    best = min(grid, key=bowl)
    assert scan.shift == best and scan.statistic == bowl(0) and scan.best == pytest.approx(bowl(best))
    assert scan.ratio == pytest.approx(max(1.0, bowl(0) / bowl(best)))
    assert set(model.read) <= set(grid) and len(set(model.read)) == len(model.read) < len(grid) / 3


def test_the_check_fires_on_a_far_shift_that_explains_the_record_much_better():
    assert TimingScan(40, 2.0, 0.6, 0.3).off(RATE)  # 2 ms, twice as well
    assert not TimingScan(40, 1.5, 0.45, 0.3).off(RATE)  # not enough better
    assert not TimingScan(4, 10.0, 0.9, 0.09).off(RATE)  # 0.2 ms: the answer's own jitter
    assert TimingScan(6, 10.0, 0.9, 0.09).off(RATE)  # 0.3 ms
    assert not TimingScan(40, 2.0, 0.6, 0.3).off(RATE, threshold=2.5)  # a pipeline's own, looser threshold
    assert not TimingScan(40, 3.7, 1.1, 0.3).off(RATE)  # inconsistent as it came: refused already, cause unknown
    assert "lag the pipeline's time grid by 2.00 ms" in TimingScan(40, 2.0, 0.6, 0.3).message(RATE)
    assert "lead it by 3.00 ms" in TimingScan(-60, 2.0, 0.6, 0.3).message(RATE)


def test_a_contract_takes_a_pipelines_own_threshold_only_when_looser_and_none_without_one():
    from types import SimpleNamespace

    m = SimpleNamespace()
    assert InputContract.of(m, {}, None).timing_ratio is None  # not calibrated: the check is skipped
    assert InputContract.of(m, {"timing_ratio_max": 2.4}, None).timing_ratio == 2.4
    assert InputContract.of(m, {"timing_ratio_max": 1.2}, None).timing_ratio == TIMING_RATIO


def test_a_record_widens_its_intervals_to_a_best_shift_beyond_the_tolerance_below_refusal():
    # 2 ms late (40 samples at 20 kHz), explained 1.1 x better there (far below refusal), consistent as it came
    scan = TimingScan(40, 1.1, 0.6, 0.55)
    assert scan.widens(RATE, 1e-3) and not scan.off(RATE, 1.8)
    assert not scan.widens(RATE, 0.0)  # an exact timing: nothing widened
    assert not scan.widens(RATE, 2e-3)  # within the tolerance: its readings hold it already
    assert not TimingScan(40, 1.5, 1.2, 0.8).widens(RATE, 1e-3)  # inconsistent as it came
    assert around(10001, 40) == [36, 38, 40, 42, 44] and around(10001, 250) == [246, 248, 250]


@pytest.fixture(scope="module")
def pretrained():
    from phm_torch.online.loaded import TorchScriptPipeline

    torch.set_num_threads(1)
    module = torch.jit.load(str(PIPELINE))
    nominal = module.nominal_record.double()
    rms = float(nominal.pow(2).mean().sqrt())
    g = torch.Generator().manual_seed(3)
    noisy = nominal + 0.01 * rms * torch.randn(nominal.numel(), generator=g, dtype=torch.float64)
    return TorchScriptPipeline(module, read_metadata(PIPELINE)), noisy


@pytest.mark.torchscript  # the shipped TorchScript file
def test_phm_predict_refuses_a_current_only_record_moved_by_milliseconds_and_names_the_shift(pretrained):
    from phm_torch.online.diagnosis import diagnose

    model, noisy = pretrained
    contract = InputContract.of(model, model.metadata, None)
    assert contract.timing_ratio >= TIMING_RATIO  # the shipped file's own (scripts/add_timing_check.py)
    t = torch.arange(noisy.numel(), dtype=torch.float64) / RATE
    on_time = diagnose(model, Record(t, None, None, noisy), contract)
    assert "timing" not in on_time["ood_reasons"] and on_time["timing_check"]["ok"]
    assert abs(on_time["timing_check"]["best_shift_s"]) < 3e-4
    for samples in (100, -60):  # 5 ms late, 3 ms early
        out = diagnose(model, Record(t, None, None, delayed(noisy, samples)), contract)
        assert out["out_of_distribution"] and "timing" in out["ood_reasons"], (samples, out["ood_reasons"])
        assert out["timing_check"]["best_shift_s"] == pytest.approx(samples / RATE, abs=3e-4)
        assert out["timing_check"]["ratio"] >= TIMING_RATIO and not out["timing_check"]["ok"]
        assert any("moved in time" in m for m in out["messages"])
    # with its command column on time, the current delayed alone is refused the same way
    command = contract.command
    assert command is None  # the pipeline's command is not needed to scan; a column without it is not checked
    full = diagnose(model, Record(t, torch.zeros_like(t), None, delayed(noisy, 100)), contract)
    assert "timing" in full["ood_reasons"]
    # a pipeline without its own threshold is not scanned: the check is listed as skipped
    bare = diagnose(model, Record(t, None, None, delayed(noisy, 100)), InputContract.of(model, {}, None))
    assert bare["timing_check"] is None and "timing" in bare["checks_skipped"] and "timing" not in bare["ood_reasons"]


@pytest.mark.torchscript
def test_the_calibration_keeps_the_default_on_records_on_time_and_loosens_on_records_that_are_not(pretrained):
    model, noisy = pretrained
    rms = float(noisy.pow(2).mean().sqrt())
    g = torch.Generator().manual_seed(4)
    on_time = noisy + 0.01 * rms * torch.randn(noisy.numel(), generator=g, dtype=torch.float64)
    assert calibrate_timing_ratio(model, on_time.unsqueeze(0), RATE) == TIMING_RATIO
    late = torch.stack([on_time, delayed(noisy, 100)])  # one of two records late: the 0.995 quantile is its ratio
    noise = float(model.noise_level(late[1:].to(model.dtype))[0])
    scan = timing_scan(model, late[1], noise)
    assert scan.ratio > 2 * TIMING_RATIO
    assert calibrate_timing_ratio(model, late, RATE) == pytest.approx(scan.ratio, rel=1e-6)
    assert calibrate_timing_ratio(model, late, RATE, quantile=0.3) == TIMING_RATIO  # the one on time
    assert calibrate_timing_ratio(model, late[:0], RATE) is None  # nothing to calibrate on


@pytest.mark.torchscript  # the shipped TorchScript file
@pytest.mark.slow  # simulates 2 HF records (about a minute) and reads 56 records with their scans
def test_the_evaluation_script_refuses_records_10_ms_late_and_keeps_the_clean_ones(tmp_path):
    from script_module import script_module

    script = script_module("timing_check_eval")
    script.DELAYS_MS, script.FULL_DELAYS_MS = (10.0,), (10.0,)
    with pytest.raises(ValueError, match="--vectors must be >= 1, got 0"):
        script.main(["--vectors", "0"])
    report = script.main(["--vectors", "2", "--cache", str(tmp_path / "cache"), "--out", str(tmp_path / "t.json")])
    clean = report["cases"]["clean"]
    assert clean["as_shipped"]["cases"] == 16 and clean["as_shipped"]["flagged_by_timing_alone"] == 0
    assert clean["at_inf"]["flagged"] == clean["as_shipped"]["flagged"]  # without the check: the same flags
    for key in ("current_only_+10ms", "full_current_alone_+10ms"):
        late = report["cases"][key]
        assert late["as_shipped"]["flagged"] == 2 and late["as_shipped"]["right_unflagged"] == 0, late
    assert report["threshold"] == pytest.approx(read_metadata(PIPELINE)["timing_ratio_max"])
