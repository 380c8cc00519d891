"""phm-track's timing spread (phm_torch/tracking/timing_spread.py): the share of a fleet's in-distribution inspections
the timing scan reads best moved by 0.3 ms or more, and its warning above a tenth."""

from __future__ import annotations

import pytest

from phm_torch.tracking.timing_spread import (
    OFF_SHARE,
    alignment_setting,
    decide_alignment,
    fleet_threshold,
    scan_shift,
    spread_message,
    spread_of,
    timing_spread,
)


def _inspections(shifts, ood=()):
    return [{"timing_best_shift_s": s, "out_of_distribution": i in ood} for i, s in enumerate(shifts)]


THRESHOLD = OFF_SHARE + 2 * 0.003  # the shipped pipeline's: 0.3 % of its on-time inspections read 0.3 ms off


def test_a_pipelines_threshold_follows_its_own_on_time_share_and_none_where_it_cannot_tell():
    assert fleet_threshold(0.003) == pytest.approx(THRESHOLD)
    assert fleet_threshold(None) is None  # not measured: the fleet's timing is not judged
    assert fleet_threshold(0.58) is None  # the rudder's paper-scale pipeline: its own leaning, not a bench's timing


def test_a_fleet_on_time_is_not_warned_of():
    spread = timing_spread(_inspections([0.0, 1e-4, -1e-4, 2e-4] * 5))
    assert spread["scanned"] == 20 and spread["share_off"] == 0.0 and spread_message(spread, THRESHOLD) is None


def test_a_jittered_fleet_is_warned_of_with_its_share_and_median_shift():
    shifts = [0.0, 4e-4, -5e-4, 1e-4, 5e-4, 0.0]
    spread = timing_spread(_inspections(shifts + [0.01, None], ood=(6,)))  # refused and unscanned: left out
    assert spread["scanned"] == 6 and spread["share_off"] == pytest.approx(0.5) and spread["share_off"] > OFF_SHARE
    assert spread["median_shift_s"] == pytest.approx(5e-5) and spread["median_abs_shift_s"] == pytest.approx(2.5e-4)
    line = spread_message(spread, THRESHOLD)
    assert "50 % of the 6 in-distribution inspections" in line and "Record the command column" in line
    assert spread_message(spread, None) is None  # a pipeline whose on-time share is unknown is not judged


def test_a_fleet_without_scans_has_no_spread():
    assert timing_spread(_inspections([None, None])) is None and spread_message(None, THRESHOLD) is None


def test_the_alignment_setting_is_auto_true_or_false_and_refused_by_name_otherwise():
    assert alignment_setting("auto") == "auto" and alignment_setting(True) is True and alignment_setting(False) is False
    for bad in ("yes", 1, 0, None):
        with pytest.raises(ValueError, match="timing_align must be auto, true or false"):
            alignment_setting(bad)


def test_auto_aligns_a_fleet_whose_first_inspections_timing_scatters():
    def diagnosis(shift, ood=False, aligned=None):
        return {"out_of_distribution": ood, "timing_check": {"best_shift_s": shift}, "timing_aligned_s": aligned}

    on_time = [diagnosis(s) for s in (0.0, 1e-4, -1e-4, 0.0, 2e-4)]
    jittered = [diagnosis(s) for s in (5e-4, -4e-4, 0.0, 1e-4, -5e-4)]
    assert decide_alignment("auto", on_time, THRESHOLD) == (False, spread_of([0.0, 1e-4, -1e-4, 0.0, 2e-4]))
    assert decide_alignment("auto", jittered, THRESHOLD)[0] and decide_alignment(False, jittered, THRESHOLD)[0] is False
    assert decide_alignment("auto", jittered, None)[0] is False  # no threshold: never aligned by itself
    assert decide_alignment(True, on_time, None)[0] is True
    assert decide_alignment("auto", [diagnosis(5e-4, ood=True)], THRESHOLD) == (False, None)  # refused: not counted
    assert decide_alignment("auto", jittered[:4], THRESHOLD)[0] is False  # too few first inspections to decide on
    # an aligned inspection counts with the shift it was read at before (its re-read scan is then near 0)
    assert spread_of([scan_shift(diagnosis(0.0, aligned=5e-4))])["share_off"] == 1.0
