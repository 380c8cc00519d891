"""Whether a fleet's inspections came on time: the timing scan's best shift over its in-distribution inspections.

phm-track's filter reads each inspection at its own timing (its measurement model is the pipeline's on-time
intervals), and near nominal the FDI reads a fraction of a millisecond of timing as damage (gain drift). Measured on
the pretrained pipeline over 100 run-to-failure histories of the reference actuator (1,728 inspections, current-only
records): on time, its 5-95 % band held the true RUL at 91 % of the inspections and every end of life was flagged
within one inspection; with each record's trigger moved by up to +-0.5 ms at random, 16 % and 18 % (72 % flagged
early). The timing scan (:mod:`~phm_torch.online.timing_check`) sees it on such near-nominal records: its best shift
lay ``MIN_SHIFT_S`` (0.3 ms) or more away on 5 of 1,727 on-time inspections, on 51 % of the jittered ones, and on
every one of 288 read 0.5 ms late (mean best shift 9.9 of 10 samples). So phm-track reports the share of inspections
read best moved that far (``metrics.json`` ``timing``) and warns above the pipeline's own threshold
(:func:`fleet_threshold`, from the on-time share its ``.tracker_check.json`` records: the shipped pipeline's 0.3 %), and
with ``timing_align`` (``auto`` by default: where that share of the fleet check's first inspections passes it) reads every
inspection again moved back by its scan shift, within ``ALIGN_TOLERANCE_S``: on the jittered histories coverage 16 ->
91 %, ends of life flagged within one inspection 18 -> 75 % (20 % early instead of 72 %). A fleet on time is not
aligned (aligning it anyway: coverage 91 %, ends of life in time 100 -> 77 %, the scan's own error near nominal).
"""

from __future__ import annotations

import statistics
from collections.abc import Iterable, Mapping
from typing import Any

from ..online.timing_check import MIN_SHIFT_S

OFF_SHARE = 0.1  # a fleet read best moved 0.3 ms or more this much more often than on time is warned of (and aligned)
UNTELLABLE = 0.5  # a pipeline whose own threshold would reach this cannot tell a fleet's timing from its own leaning
MIN_SCANNED = 5  # first inspections auto decides on, at least (the fleet check's own minimum, min_actuators)
ALIGN_SETTINGS = ("auto", True, False)
# an aligned inspection is read within this too: near nominal the scan's best shift lay within 4 samples (0.2 ms at
# 20 kHz) of the truth on 99.7 % of 288 on-time inspections (jittered fleet, aligned: coverage 67 % without it, 91 %)
ALIGN_TOLERANCE_S = 2e-4


def alignment_setting(value: Any) -> str | bool:
    """phm-track's ``timing_align`` checked: ``auto``, true or false; ValueError naming the field otherwise."""
    if value in ALIGN_SETTINGS and not (isinstance(value, int) and not isinstance(value, bool)):
        return value
    raise ValueError(f"timing_align must be auto, true or false, got {value!r}")


def read_shift(diagnosis: Mapping[str, Any]) -> float | None:
    """The timing scan's best shift [s] of one diagnosis as it came, before any alignment (``track.json``'s
    ``timing_best_shift_s``); None without a scan."""
    if diagnosis.get("timing_aligned_s") is not None:
        return float(diagnosis["timing_aligned_s"])
    return (diagnosis.get("timing_check") or {}).get("best_shift_s")


def scan_shift(diagnosis: Mapping[str, Any]) -> float | None:
    """:func:`read_shift` of an in-distribution diagnosis, None for one out of distribution."""
    return None if diagnosis["out_of_distribution"] else read_shift(diagnosis)


def spread_of(shifts: Iterable[float | None]) -> dict[str, Any] | None:
    """{scanned, share_off, median_shift_s, median_abs_shift_s} of the scan shifts [s] given (None: not scanned);
    None where none was."""
    kept = [float(s) for s in shifts if s is not None]
    if not kept:
        return None
    return {
        "scanned": len(kept),
        "share_off": sum(abs(s) >= MIN_SHIFT_S for s in kept) / len(kept),
        "median_shift_s": statistics.median(kept),
        "median_abs_shift_s": statistics.median(abs(s) for s in kept),
    }


def timing_spread(inspections: Iterable[Mapping[str, Any]]) -> dict[str, Any] | None:
    """:func:`spread_of` the in-distribution inspections of ``track.json`` (their ``timing_best_shift_s``)."""
    return spread_of(i.get("timing_best_shift_s") for i in inspections if not i["out_of_distribution"])


def fleet_threshold(on_time_share: float | None) -> float | None:
    """The share of a fleet's inspections read best 0.3 ms or more away above which its timing is off, for a pipeline
    whose own on-time histories were read so ``on_time_share`` of the time (its ``.tracker_check.json``):
    ``OFF_SHARE`` above twice that; None where that is unknown, or at ``UNTELLABLE`` or more (the 270 V rudder's
    paper-scale pipeline reads 58 % of its on-time inspections best 0.3 ms away, median -0.3 ms: the scan cannot tell a
    bench's timing from the pipeline's own leaning there)."""
    if on_time_share is None:
        return None
    threshold = OFF_SHARE + 2.0 * float(on_time_share)
    return None if threshold >= UNTELLABLE else threshold


def decide_alignment(
    setting: str | bool, first: Iterable[Mapping[str, Any]], threshold: float | None
) -> tuple[bool, dict[str, Any] | None]:
    """Whether phm-track reads every inspection moved back by its scan shift, and the spread it decided on: ``auto``
    aligns where more than ``threshold`` (:func:`fleet_threshold`; None: never) of the fleet's first inspections
    (``first``: their diagnoses, read unaligned; ``MIN_SCANNED`` of them at least) are read best 0.3 ms or more
    away."""
    spread = spread_of(scan_shift(d) for d in first)
    if setting != "auto":
        return bool(setting), spread
    if spread is None or threshold is None or spread["scanned"] < MIN_SCANNED:
        return False, spread
    return spread["share_off"] > threshold, spread


def spread_message(spread: Mapping[str, Any] | None, threshold: float | None, aligned: bool = False) -> str | None:
    """A warning where more than ``threshold`` (:func:`fleet_threshold`; None: no warning) of the scanned inspections
    are read best 0.3 ms or more away."""
    if spread is None or threshold is None or spread["share_off"] <= threshold:
        return None
    head = (
        f"the timing scan reads {100.0 * spread['share_off']:.0f} % of the {spread['scanned']} in-distribution "
        f"inspections best moved by {1000.0 * MIN_SHIFT_S:.1f} ms or more (median shift "
        f"{1000.0 * spread['median_shift_s']:+.2f} ms): their current's timing is off (a current-only record's "
        "trigger offset or jitter, a current channel's own lag). "
    )
    if aligned:
        return head + (
            "Each was read moved back by its shift (timing_align): with current-only records jittered by +-0.5 ms "
            "that kept the band's coverage at 91 % instead of 16 %, but 20 % of the ends of life came early instead of "
            "none on time (docs/prognostics.md); record the command column (the trigger is then aligned on it)"
        )
    return head + (
        "The tracker reads records on time: with current-only records jittered by +-0.5 ms its band held the true RUL "
        "at 16 % of the inspections instead of 91 % and 72 % of the ends of life came early (docs/prognostics.md). "
        "Record the command column (the trigger is then aligned on it), or set timing_align=true"
    )
