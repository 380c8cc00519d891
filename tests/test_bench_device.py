"""scripts/bench_device.py, the accelerator benchmark, on this machine's CPU (no GPU in CI): its sections run, its
rates are per whole chirp, and its online section compares the device's answers with the CPU's."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import pytest
from script_module import script_module

ROOT = Path(__file__).resolve().parents[1]


def test_simulate_rate_is_per_whole_chirp():
    import torch

    bench = script_module("bench_device")
    r = bench.bench_simulate(torch.device("cpu"), "lf", 8, 0.002, False, 1)
    assert r["fidelity"] == "lf" and r["batch"] == 8 and r["peak_gpu_gb"] is None
    # 8 signals of 2 ms in wall_s: 8 * 0.002 / 0.5 whole chirps
    assert r["signals_per_s"] == pytest.approx(8 * 0.002 / 0.5 / r["wall_s"][0])


@pytest.mark.torchscript
def test_the_script_writes_every_section_and_equal_answers_on_one_device(tmp_path, monkeypatch):
    out = tmp_path / "bench.json"
    argv = ["bench_device.py", "--device", "cpu", "--duration", "0.002", "--sim-batch", "4", "--online-batch", "8"]
    argv += ["--repeats", "3", "--cpu-threads", "1", "--cpu-sim-batch", "4", "--work", "16", "--out", str(out)]
    monkeypatch.setattr(sys, "argv", argv)
    monkeypatch.chdir(ROOT)
    script_module("bench_device").main()
    report = json.loads(out.read_text())
    assert report["machine"]["device"] == "cpu"
    errors = {k: v["error"] for k, v in report.items() if isinstance(v, dict) and "error" in v}
    assert not errors
    assert {"simulate_hf_4", "simulate_lf_4", "simulate_hf_4_cpu@1", "online"} <= set(report)
    online = report["online"]
    assert online["max_rel_diff_vs_cpu"] == {"k_hat": 0.0, "rul": 0.0}  # the same device: the same numbers
    assert online["cpu"]["records_per_s_8"] > 0 and online["cpu"]["one_record_us"]["p50"] > 0


def test_bad_duration_is_refused(monkeypatch, capsys):
    monkeypatch.setattr(sys, "argv", ["bench_device.py", "--device", "cpu", "--duration", "2"])
    with pytest.raises(SystemExit) as e:
        script_module("bench_device").main()
    assert e.value.code == 2 and "--duration must be in (0, 0.5], got 2.0" in capsys.readouterr().err
