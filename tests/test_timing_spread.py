"""phm-track's timing spread (phm_torch/tracking/timing_spread.py): the share of a fleet's in-distribution inspections
the timing scan reads best moved by 0.3 ms or more, and its warning above a tenth."""

from __future__ import annotations

import pytest

from phm_torch.tracking.timing_spread import OFF_SHARE, spread_message, timing_spread


def _inspections(shifts, ood=()):
    return [{"timing_best_shift_s": s, "out_of_distribution": i in ood} for i, s in enumerate(shifts)]


def test_a_fleet_on_time_is_not_warned_of():
    spread = timing_spread(_inspections([0.0, 1e-4, -1e-4, 2e-4] * 5))
    assert spread["scanned"] == 20 and spread["share_off"] == 0.0 and spread_message(spread) is None


def test_a_jittered_fleet_is_warned_of_with_its_share_and_median_shift():
    shifts = [0.0, 4e-4, -5e-4, 1e-4, 5e-4, 0.0]
    spread = timing_spread(_inspections(shifts + [0.01, None], ood=(6,)))  # refused and unscanned: left out
    assert spread["scanned"] == 6 and spread["share_off"] == pytest.approx(0.5) and spread["share_off"] > OFF_SHARE
    assert spread["median_shift_s"] == pytest.approx(5e-5) and spread["median_abs_shift_s"] == pytest.approx(2.5e-4)
    line = spread_message(spread)
    assert "50 % of the 6 in-distribution inspections" in line and "Record the command column" in line


def test_a_fleet_without_scans_has_no_spread():
    assert timing_spread(_inspections([None, None])) is None and spread_message(None) is None
