"""Bench lines (phm_torch/online/bench_lines.py): a sinusoid of one frequency, amplitude and phase through a whole record
is found to a small fraction of a hertz and removed to well under the record's noise; what a chirp puts at a
frequency (it comes and goes) and a tone that changes halfway are no line; phm-predict's record removes a hum from a
near-nominal record and reads it as the clean one."""

from __future__ import annotations

import math
from pathlib import Path

import pytest
import torch

from phm_torch.faults import FAULT_NAMES
from phm_torch.online.bench_lines import LINE_BACKLASH, find_lines, line_possible, remove_lines

RATE = 20000.0
PIPELINE = Path(__file__).resolve().parents[1] / "pretrained" / "online_surrogates_best.pt"


def _chirp_current(seed: int, noise: float = 0.01) -> tuple[torch.Tensor, torch.Tensor, float]:
    """A chirp-like current (10,001 samples, 0.5 s): a 0-15 Hz chirp's acceleration current with a cubic (friction's
    harmonics), and white noise; its time axis and RMS."""
    t = torch.arange(10001, dtype=torch.float64) / RATE
    phase = 2.0 * math.pi * 15.0 * t * t
    x = torch.sin(phase) + 0.3 * torch.sin(phase) ** 3 + 0.2 * torch.sin(2.0 * phase)
    rms = float(x.pow(2).mean().sqrt())
    g = torch.Generator().manual_seed(seed)
    return x + noise * rms * torch.randn(x.numel(), generator=g, dtype=torch.float64), t, rms


def test_a_chirp_record_has_no_line():
    for seed in range(3):
        x, _, _ = _chirp_current(seed)
        assert find_lines(x, RATE) == []


@pytest.mark.parametrize("frequency", [400.0, 1234.5, 3000.0])
def test_a_hum_is_found_and_removed_to_under_the_noise(frequency):
    x, t, rms = _chirp_current(1)
    hum = 0.2 * rms * torch.cos(2.0 * math.pi * frequency * t + 1.0)
    lines = find_lines(x + hum, RATE)
    assert len(lines) == 1
    line = lines[0]
    assert line.frequency == pytest.approx(frequency, abs=0.01)
    assert line.share == pytest.approx(0.2, rel=0.02)
    assert math.cos(line.phase - 1.0) > 0.999
    left = remove_lines(x + hum, t, lines) - x
    assert float(left.pow(2).mean().sqrt()) < 0.002 * rms  # the noise is 1 %


def test_a_hum_and_its_harmonic_are_two_lines_and_missing_samples_are_no_obstacle():
    x, t, rms = _chirp_current(2)
    y = x + 0.1 * rms * torch.cos(2.0 * math.pi * 400.0 * t) + 0.05 * rms * torch.cos(2.0 * math.pi * 800.0 * t + 2.0)
    y[::97] = math.nan
    lines = find_lines(y, RATE)
    assert sorted(round(line.frequency) for line in lines) == [400, 800]
    assert torch.isnan(remove_lines(y, t, lines)[::97]).all()


def test_a_tone_that_changes_halfway_or_comes_and_goes_is_no_line():
    x, t, rms = _chirp_current(3)
    tone = 0.2 * rms * torch.cos(2.0 * math.pi * 400.0 * t)
    halves = torch.where(t < 0.25, tone, 3.0 * tone)  # the amplitude triples halfway (a limit cycle growing)
    assert find_lines(x + halves, RATE) == []
    burst = torch.where((t > 0.1) & (t < 0.2), tone, torch.zeros_like(tone))
    assert find_lines(x + burst, RATE) == []
    assert find_lines(x + 0.002 * rms * torch.cos(2.0 * math.pi * 400.0 * t), RATE) == []  # under LINE_MIN


def test_bad_rate_is_refused_and_a_short_record_has_no_line():
    x, _, _ = _chirp_current(0)
    with pytest.raises(ValueError, match="sample rate"):
        find_lines(x, 0.0)
    assert find_lines(x[:100], RATE) == []


def test_which_answers_may_make_a_line_themselves():
    k = torch.zeros(8, dtype=torch.float64)
    assert not line_possible(k)
    k[FAULT_NAMES.index("backlash")] = LINE_BACKLASH
    assert line_possible(k)
    k = torch.zeros(8, dtype=torch.float64)
    k[FAULT_NAMES.index("short_a")] = 0.9
    assert not line_possible(k)  # one shorted phase: no line seen
    k[FAULT_NAMES.index("short_c")] = 0.5
    assert line_possible(k)


@pytest.mark.torchscript  # the shipped TorchScript file
def test_phm_predict_removes_a_hum_from_a_near_nominal_record_and_reads_the_clean_one():
    from phm_torch.online.corruptions import Record
    from phm_torch.online.diagnosis import diagnose
    from phm_torch.online.input_contract import InputContract
    from phm_torch.online.loaded import TorchScriptPipeline

    torch.set_num_threads(1)
    module = torch.jit.load(str(PIPELINE))
    model = TorchScriptPipeline(module, {})
    contract = InputContract.of(model, {}, None)
    nominal = module.nominal_record.double()
    rms = float(nominal.pow(2).mean().sqrt())
    g = torch.Generator().manual_seed(5)
    clean = nominal + 0.01 * rms * torch.randn(nominal.numel(), generator=g, dtype=torch.float64)
    t = torch.arange(nominal.numel(), dtype=torch.float64) / RATE
    right = diagnose(model, Record(t, None, None, clean), contract)
    hum = 0.2 * rms * torch.sin(2.0 * math.pi * 400.0 * t + 0.3)
    humming = diagnose(model, Record(t, None, None, clean + hum), contract)
    assert right["bench_lines"] == [] and len(humming["bench_lines"]) == 1
    assert humming["bench_lines"][0]["frequency"] == pytest.approx(400.0, abs=0.05)
    assert any("hum on the bench's probe" in m for m in humming["messages"])
    assert humming["out_of_distribution"] == right["out_of_distribution"]
    for name in FAULT_NAMES:
        assert humming["k_hat"][name] == pytest.approx(right["k_hat"][name], abs=5e-3), name


@pytest.mark.torchscript  # the shipped TorchScript file
@pytest.mark.slow  # simulates 2 HF records (about a minute with the diagnoses on 2 cores)
def test_the_corrections_script_reads_a_40_percent_hum_and_a_2_percent_offset_as_the_clean_records(tmp_path):
    from script_module import script_module

    script = script_module("record_corrections_eval")
    script.HUMS, script.OFFSETS, script.COLOURED = ((0.0, 400.0), (0.4, 400.0)), (0.02,), ()
    with pytest.raises(ValueError, match="--vectors must be >= 1, got 0"):
        script.main(["--vectors", "0"])
    report = script.main(["--vectors", "2", "--cache", str(tmp_path / "cache"), "--out", str(tmp_path / "h.json")])
    clean, hum = report["hums"]
    assert clean["as_read"] == clean["removed"] and report["clean"]["lines_removed"] == 0
    assert hum["removed"]["right_unflagged"] == clean["as_read"]["right_unflagged"]
    assert hum["removed"]["err_k_median"] == pytest.approx(clean["as_read"]["err_k_median"], abs=0.01)
    offset = report["offsets"][0]  # 2 %, within the offset check: removed at rest, read as the clean records
    assert offset["right_unflagged"] == clean["as_read"]["right_unflagged"] and offset["flagged"] == 0


@pytest.mark.torchscript  # the shipped TorchScript file
def test_a_humming_bench_reads_as_a_quiet_one_through_its_baseline(compose, tmp_path):
    """phm-predict with a baseline: the bench hums at 400 Hz on its healthy record and on the measurement (other
    phases); both lines are removed, and the answer is the quiet bench's."""
    from phm_torch.apps.predict import predict

    module = torch.jit.load(str(PIPELINE))
    nominal = module.nominal_record.double()
    rms = float(nominal.pow(2).mean().sqrt())
    t = torch.arange(nominal.numel(), dtype=torch.float64) / RATE
    g = torch.Generator().manual_seed(4)
    bench = nominal * 1.01 + 0.01 * rms * torch.randn(nominal.numel(), generator=g, dtype=torch.float64)
    measured = nominal * 1.01 + 0.01 * rms * torch.randn(nominal.numel(), generator=g, dtype=torch.float64)

    def csv(name, x):
        path = tmp_path / name
        path.write_text("time,current\n" + "\n".join(f"{a!r},{b!r}" for a, b in zip(t.tolist(), x.tolist())) + "\n")
        return path

    def hum(phase):
        return 0.2 * rms * torch.sin(2.0 * math.pi * 400.0 * t + phase)

    answers = []
    for loud in (0.0, 1.0):
        base, rec = csv(f"base{loud}.csv", bench + loud * hum(0.4)), csv(f"rec{loud}.csv", measured + loud * hum(2.0))
        _, out = predict(compose("predict", [f"pipeline={PIPELINE}", f"measurements=[{rec}]", f"baseline=[{base}]"]))
        answers.append(out["records"][0])
    quiet, humming = answers
    assert quiet["bench_lines"] == [] and len(humming["bench_lines"]) == 1
    assert humming["out_of_distribution"] == quiet["out_of_distribution"]
    for name in FAULT_NAMES:
        assert humming["k_hat"][name] == pytest.approx(quiet["k_hat"][name], abs=5e-3), name


def _workbench_record(current: torch.Tensor, t: torch.Tensor, position: torch.Tensor):
    from phm_torch.workbench.data import Record as BenchRecord

    return BenchRecord("r", t, position.clone(), {"position": position, "current": current}, RATE)


def test_the_workbench_removes_a_line_the_model_does_not_make_and_keeps_the_rest():
    from phm_torch.workbench.bench_lines import bench_lines, without_lines

    x, t, rms = _chirp_current(6)
    position = 5e-3 * torch.sin(2.0 * math.pi * 15.0 * t * t)  # a chirp about zero: no steady speed
    hum = 0.1 * rms * torch.cos(2.0 * math.pi * 400.0 * t + 0.7)
    records = [_workbench_record(x + hum, t, position)]
    found = bench_lines(records, [{"current": x}], gear_ratio=100.0, max_order=48)
    assert [round(line.frequency) for line in found["r"]] == [400]
    cleaned = without_lines(records, found)[0].measured["current"]
    assert float((cleaned - x).pow(2).mean().sqrt()) < 0.002 * rms
    # the model makes the same line (an effect it holds): not the bench's
    assert bench_lines(records, [{"current": x + hum}], gear_ratio=100.0, max_order=48) == {}
    # a steady slew of 20 rad/s at the output turns the motor at 2,000 rad/s: a line at its order 6 (1909.9 Hz) may be
    # the rotor's (cogging at a steady speed, which the model without that effect does not make): kept; the same line
    # under a chirp about zero is the bench's
    slew = 20.0 * t
    rotor = 0.1 * rms * torch.cos(2.0 * math.pi * (6 * 2000.0 / (2.0 * math.pi)) * t)
    steady = [_workbench_record(x + rotor, t, slew)]
    assert bench_lines(steady, [{"current": x}], gear_ratio=100.0, max_order=48) == {}
    assert bench_lines([_workbench_record(x + rotor, t, position)], [{"current": x}], 100.0, 48) != {}
