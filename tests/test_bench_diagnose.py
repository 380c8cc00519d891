"""scripts/bench_diagnose.py: phm-predict's per-record diagnosis timed on the suite's records of the shipped pipeline;
its JSON holds every figure the README quotes, and the parts are no larger than the whole."""

from __future__ import annotations

import json

import pytest
from script_module import script_module

pytestmark = pytest.mark.torchscript  # the shipped TorchScript file


def test_the_diagnosis_benchmark_writes_its_figures(tmp_path):
    out = tmp_path / "bench.json"
    report = script_module("bench_diagnose").main(["--repeats", "1", "--out", str(out)])
    assert json.loads(out.read_text()) == json.loads(json.dumps(report))
    assert report["records"] == 4 and report["samples"] == 10001 and report["timing_scan_grid"] == 251
    for key in (
        "diagnose_current_only",
        "diagnose_current_only_without_timing",
        "diagnose_full_record",
        "pipeline_step",
        "timing_scan",
    ):
        assert report[key]["calls"] == 4 and 0 < report[key]["p50_ms"] <= report[key]["max_ms"], key
    # the scan is part of the current-only diagnosis: it cannot cost more than the whole
    assert report["timing_scan"]["p50_ms"] < report["diagnose_current_only"]["p50_ms"]
    with pytest.raises(ValueError, match="--repeats must be >= 1"):
        script_module("bench_diagnose").main(["--repeats", "0", "--out", str(out)])
