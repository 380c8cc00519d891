"""The tracker's figures on simulated histories of a pipeline's actuator: thresholds, JSON round trip, bad files."""

from __future__ import annotations

import json

import pytest

from phm_torch.tracking.tracker_check import COVERAGE_WARNING, EARLY_WARNING, TrackerCheck

RULE = {"verdict": "posterior", "faulty_at": "p5"}


def test_figures_from_phm_track_metrics_round_trip_and_warn_only_where_short(tmp_path):
    metrics = {
        "actuators": 60,
        "inspections": 1200,
        "tracker": {"coverage_5_95": 0.87, "alpha_lambda": 0.8, "eol_flagged_early": 0.05, "snapshot_only": 3.0},
    }
    check = TrackerCheck.from_metrics(metrics, RULE, {"probe_k_hat": [0.0] * 8})
    assert check.figures["coverage_5_95"] == 0.87 and check.figures["prognostic_horizon"] is None
    assert "snapshot_only" not in check.figures and check.warnings() == []  # the reference's figures: nothing said
    check.save(tmp_path / "c.json")
    assert TrackerCheck.load(tmp_path / "c.json") == check
    short = TrackerCheck({"coverage_5_95": COVERAGE_WARNING - 0.01, "eol_flagged_early": EARLY_WARNING}, RULE, 6, 83)
    (line,) = short.warnings()  # the early share at its threshold is not announced
    assert "held the true RUL on 69 % of the inspections" in line and "rule posterior/p5" in line
    assert len(short.warnings(RULE)) == 1
    assert short.warnings({"verdict": "record", "faulty_at": "p5"})[-1].endswith("was not the one measured")


def test_the_on_time_share_of_the_timing_scan_travels_with_the_figures_only_when_read_unaligned(tmp_path):
    metrics = {"actuators": 40, "inspections": 700, "tracker": {"coverage_5_95": 0.9}}
    timing = {"scanned": 700, "share_off": 0.012, "median_shift_s": 0.0, "median_abs_shift_s": 1e-4}
    check = TrackerCheck.from_metrics({**metrics, "timing": {**timing, "aligned": False}}, RULE, {})
    assert check.timing_share_off == 0.012
    check.save(tmp_path / "c.json")
    assert TrackerCheck.load(tmp_path / "c.json").timing_share_off == 0.012
    assert (
        TrackerCheck.from_metrics({**metrics, "timing": {**timing, "aligned": True}}, RULE, {}).timing_share_off is None
    )
    assert TrackerCheck.from_metrics(metrics, RULE, {}).timing_share_off is None  # no scan


def test_bad_figures_and_files_are_named(tmp_path):
    with pytest.raises(ValueError, match="coverage_5_95 must be in"):
        TrackerCheck({"coverage_5_95": 41.0}, RULE, 6, 83)
    with pytest.raises(ValueError, match="unknown figures"):
        TrackerCheck({"coverage": 0.4}, RULE, 6, 83)
    with pytest.raises(ValueError, match="histories must be >= 1"):
        TrackerCheck({}, RULE, 0, 0)
    (tmp_path / "a.json").write_text(json.dumps({"format": "other"}))
    with pytest.raises(ValueError, match="not a phm_torch.tracker_check/1 file"):
        TrackerCheck.load(tmp_path / "a.json")
    (tmp_path / "b.json").write_text(json.dumps({"format": "phm_torch.tracker_check/1", "figures": {}}))
    with pytest.raises(ValueError, match="'rule' missing"):
        TrackerCheck.load(tmp_path / "b.json")
    with pytest.raises(ValueError, match="cannot read it"):
        TrackerCheck.load(tmp_path / "none.json")
