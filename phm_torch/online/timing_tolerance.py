"""The current's timing tolerance: a record's k intervals widened to every reading within it.

The FDI reads the current's timing to the sample, and its k intervals are calibrated on records exactly on time. On
the pretrained pipeline (300 held-out records of the seed-77 store, 1 % noise) a current moved by 4 samples (0.2 ms)
left every damage inside its interval on 27 % of the records (93 % on time), by 10 samples (0.5 ms) on 5 %, while the
error itself grew little (err_k 3.7 -> 5.4 %); its verdict went from 97 to 69 % right, healthy records read faulty:
the FDI reads the delay as the phase lag of a lower loop gain (gain drift 0.08 lower on average, 0.09 higher 0.5 ms
early), and the health boundary of the gain drift lies near nominal. A record with its command
column is aligned on it (a trigger offset is found and removed); a current-only record (the paper's own input) has
nothing to align on, and below a few milliseconds the ``timing`` check (:mod:`.timing_check`) cannot tell a late
record from one on time: the consistency statistic's own jitter between neighbouring shifts is as large.

So for a current-only record phm-predict reads the record again at each shift within ``TIMING_TOLERANCE_S`` (the
timing check's grid: every second sample of the reference's record) and reports the union of the k intervals: a
record late or early by up to the tolerance has its on-time reading among them, so its intervals hold the truth as
the on-time one's do. The answer (k_hat, the verdict, P(faulty), the RUL) stays the reading as it came; where the
verdict differs within the tolerance, the record says so. Measured on the 300 records: within +-1 ms every damage
inside its interval on 98 % of them on time and up to 1 ms off (median width 0.017 -> 0.067; +-0.5 ms: 97 %, 0.046),
and the verdict changes within the tolerance on 60 % of these near-boundary records (51 % at +-0.5 ms). On 500
val-like vectors on phm-predict's path (``scripts/timing_check_eval.py``, docs/trust/timing_check_pretrained.json):
wrong and unflagged, exact trigger -> 1 ms tolerance, 420 -> 188 of 4,000 clean records (119 of them with the verdict
said to change), 465 -> 108 of 500 records 0.5 ms late (101), 450 -> 116 at 1 ms late (92).

A record with its command column is aligned on it, but its current channel may still lag the command and position
channels by its own delay (a probe's or anti-alias filter's group delay, a second logger): on the pretrained pipeline
465 of 500 val-like records whose current alone lagged by 0.5 ms were answered wrong, unflagged, exactly as the
current-only records 0.5 ms late. So the same tolerance holds for that channel's lag (since 2026-11-30): the aligned
current is read at every shift within it. A bench whose trigger and channels are known to be aligned to the sample
sets the tolerance to 0.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import torch

from .command_check import shifted
from .timing_check import around, scan_shifts

TIMING_TOLERANCE_S = 1e-3  # [s] phm-predict's default (conf/predict.yaml `timing_tolerance: null`)


def tolerance_seconds(value: Any, field: str = "timing_tolerance") -> float:
    """``value`` as a tolerance [s] (None: ``TIMING_TOLERANCE_S``); ValueError naming ``field`` unless a finite
    number >= 0."""
    if value is None:
        return TIMING_TOLERANCE_S
    if isinstance(value, bool) or not isinstance(value, int | float) or not math.isfinite(value) or value < 0:
        raise ValueError(f"{field} must be a number of seconds >= 0 (or null: {TIMING_TOLERANCE_S:g} s), got {value!r}")
    return float(value)


def tolerance_shifts(n: int, sample_rate: float, tolerance_s: float) -> list[int]:
    """The shifts [samples] a record of ``n`` samples at ``sample_rate`` [Hz] is read at within +- ``tolerance_s``:
    the timing scan's grid (:func:`~.timing_check.scan_shifts`) within it, 0 always."""
    reach = tolerance_s * sample_rate
    return [s for s in scan_shifts(n) if abs(s) <= reach + 1e-9]


def reading_shifts(n: int, sample_rate: float, tolerance_s: float, best_shift: int | None = None) -> list[int]:
    """The shifts [samples] a record of ``n`` samples is read at: :func:`tolerance_shifts`, and around ``best_shift``
    (the timing scan's beyond the tolerance, :meth:`~.timing_check.TimingScan.widens`) where given."""
    within = tolerance_shifts(n, sample_rate, tolerance_s)
    return sorted(set(within) | set([] if best_shift is None else around(n, best_shift)))


@dataclass(frozen=True)
class ToleranceReading:
    """The union of a record's k intervals over the shifts within its trigger tolerance.

    Attributes:
        tolerance_s: the tolerance [s].
        shifts: how many readings (shifts) it took.
        lower, upper: (8,) float64 the union's bounds.
        verdict_stable: whether every reading gave the same verdict (healthy / faulty).
        healthy_share: the share of the readings that gave "healthy".
        current_only: whether the record came without its command column (its trigger is what the tolerance is for;
            with one, the current channel's own lag).
        widened_to_s: the timing scan's best shift [s] beyond the tolerance whose readings the union holds too
            (:meth:`~.timing_check.TimingScan.widens`), None: the tolerance's readings alone.
    """

    tolerance_s: float
    shifts: int
    lower: torch.Tensor
    upper: torch.Tensor
    verdict_stable: bool
    healthy_share: float
    current_only: bool = True
    widened_to_s: float | None = None

    def as_dict(self) -> dict[str, Any]:
        """The record's JSON field ``timing_tolerance`` (the bounds are in ``k_interval``)."""
        return {
            "tolerance_s": self.tolerance_s,
            "readings": self.shifts,
            "verdict_stable": self.verdict_stable,
            "healthy_share": self.healthy_share,
            "widened_to_s": self.widened_to_s,
        }

    def widened_message(self) -> str | None:
        """A line for the user where the intervals hold a reading beyond the tolerance, else None."""
        if self.widened_to_s is None:
            return None
        lag = 1000.0 * self.widened_to_s
        way = f"{lag:.2f} ms late" if lag > 0 else f"{-lag:.2f} ms early"
        return (
            f"the current is explained best read as if {way}, beyond the timing tolerance of "
            f"+-{1000.0 * self.tolerance_s:.2f} ms (not so much better that the record is refused): its k intervals "
            "hold that reading too"
        )

    def message(self) -> str | None:
        """A line for the user where the verdict changes within the tolerance, else None."""
        if self.verdict_stable:
            return None
        within = "the record's timing tolerance" if self.widened_to_s is None else "its timing tolerance and best shift"
        head = (
            f"the verdict changes within {within} of +-{1000.0 * self.tolerance_s:.2f} ms "
            f"({100.0 * self.healthy_share:.0f} % of the readings healthy): "
        )
        if self.current_only:
            return head + (
                "a current-only record's trigger is not known to the sample; record the command column with the "
                "current (the trigger is then aligned on it)"
            )
        return head + (
            "the current channel's own delay against the command column (a probe's or filter's group delay, another "
            "logger) is not known to the sample; where it is measured, remove it and set timing_tolerance to what is "
            "left"
        )


@torch.no_grad()
def read_within_tolerance(
    model: Any,
    current: torch.Tensor,
    sample_rate: float,
    tolerance_s: float,
    bench_nominal: torch.Tensor | None = None,
    current_only: bool = True,
    best_shift: int | None = None,
) -> ToleranceReading | None:
    """The record ``current`` (n_full,) [A] as the pipeline's step reads it (``bench_nominal``: the bench's healthy
    record it is rebased with; ``current_only``: the record came without its command column) read at every shift
    within +- ``tolerance_s`` and around ``best_shift`` [samples] (the timing scan's, where it widens the intervals:
    :meth:`~.timing_check.TimingScan.widens`); None where that takes no shift but 0 or the pipeline reports no k
    intervals."""
    shifts = reading_shifts(current.numel(), sample_rate, tolerance_s, best_shift)
    if len(shifts) < 2:
        return None
    x = current.double().flatten()
    block = torch.stack([shifted(x, s) for s in shifts]).to(model.dtype)
    step = model.run(block, bench_nominal)
    if step.k_lower is None:
        return None
    lower = torch.nan_to_num(step.k_lower.double(), nan=math.inf).amin(0)
    upper = torch.nan_to_num(step.k_upper.double(), nan=-math.inf).amax(0)
    healthy = (step.score > 0).double()
    share = float(healthy.mean())
    best = None if best_shift is None else best_shift / sample_rate
    return ToleranceReading(tolerance_s, len(shifts), lower, upper, share in (0.0, 1.0), share, current_only, best)
