"""Whether a fleet's inspections came on time: the timing scan's best shift over its in-distribution inspections.

phm-track's filter reads each inspection at its own timing (its measurement model is the pipeline's on-time
intervals), and near nominal the FDI reads a fraction of a millisecond of timing as damage (gain drift). Measured on
the pretrained pipeline over 100 run-to-failure histories of the reference actuator (1,728 inspections, current-only
records): on time, its 5-95 % band held the true RUL at 91 % of the inspections and every end of life was flagged
within one inspection; with each record's trigger moved by up to +-0.5 ms at random, 16 % and 18 % (72 % flagged
early). The timing scan (:mod:`~phm_torch.online.timing_check`) sees it on such near-nominal records: its best shift
lay ``MIN_SHIFT_S`` (0.3 ms) or more away on none of 288 on-time inspections, on 45 % of the jittered ones, and
on every one of those 0.5 ms late (mean best shift 9.9 of 10 samples). So phm-track reports the share of inspections
read best moved that far (``metrics.json`` ``timing``) and warns above ``OFF_SHARE``.
"""

from __future__ import annotations

import statistics
from collections.abc import Iterable, Mapping
from typing import Any

from ..online.timing_check import MIN_SHIFT_S

OFF_SHARE = 0.1  # a fleet whose inspections are read best moved 0.3 ms or more this often is warned of


def timing_spread(inspections: Iterable[Mapping[str, Any]]) -> dict[str, Any] | None:
    """{scanned, share_off, median_shift_s, median_abs_shift_s} of the in-distribution inspections of ``track.json``
    whose diagnosis ran the timing scan (``timing_best_shift_s``); None where none did."""
    shifts = [
        float(i["timing_best_shift_s"])
        for i in inspections
        if not i["out_of_distribution"] and i.get("timing_best_shift_s") is not None
    ]
    if not shifts:
        return None
    return {
        "scanned": len(shifts),
        "share_off": sum(abs(s) >= MIN_SHIFT_S for s in shifts) / len(shifts),
        "median_shift_s": statistics.median(shifts),
        "median_abs_shift_s": statistics.median(abs(s) for s in shifts),
    }


def spread_message(spread: Mapping[str, Any] | None) -> str | None:
    """A warning where more than ``OFF_SHARE`` of the scanned inspections are read best 0.3 ms or more away."""
    if spread is None or spread["share_off"] <= OFF_SHARE:
        return None
    return (
        f"the timing scan reads {100.0 * spread['share_off']:.0f} % of the {spread['scanned']} in-distribution "
        f"inspections best moved by {1000.0 * MIN_SHIFT_S:.1f} ms or more (median shift "
        f"{1000.0 * spread['median_shift_s']:+.2f} ms): their current's timing is off (a current-only record's "
        "trigger offset or jitter, a current channel's own lag). The tracker reads records on time: with current-only "
        "records jittered by +-0.5 ms its band held the true RUL at 16 % of the inspections instead of 91 % and 72 % "
        "of the ends of life came early (docs/prognostics.md). Record the command column (the trigger is then "
        "aligned on it); timing_tolerance=null widens each reading to its timing (the band's coverage back to 87 %, "
        "the ends of life still early)"
    )
