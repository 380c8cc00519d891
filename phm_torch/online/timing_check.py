"""The ``timing`` check: the record's current is read best moved in time, by the pipeline's own answer.

The FDI reads the current's timing to the sample: on the reference actuator's pretrained pipeline a current 0.5 ms
(10 samples) late left 235 of 250 val-like answers out of their intervals, unflagged, and 5 ms 232 of 250. A record
with its command column is aligned on it (:func:`~.record_corrections.align_trigger`); a current-only record (the
paper's own input) has nothing else to align on, and a current channel delayed alone (another logger, a filter's
group delay) shows in no other column. Nothing in the current marks time without a model: faults move the current's
own onset and its correlation with the nominal record by tens of samples (5-95 %: -19 to +50 on those records).

The pipeline's consistency check does (analysis by synthesis, :mod:`.consistency`): its statistic compares the record
with the one the FDI's own answer predicts. Moved back by its true delay, a delayed record is explained better than as
it came; a record on time is explained best near where it is. :func:`timing_scan` reads the statistic for the record
shifted within ``MAX_SHIFT_SHARE`` of its length (coarse to fine, to the second sample on the reference's grid), and
the check fires where the best shift
lies ``MIN_SHIFT_S`` or more away and explains the record the pipeline's threshold times better than no shift.

Measured on the pretrained pipeline (``scripts/timing_check_eval.py``, docs/trust/timing_check_pretrained.json): over
4,000 clean val-like records (0-3 % noise) the ratio of the records whose best shift lay that far reached 1.93 (0.997
quantile 1.76); at its threshold of 1.877 the check refused 1 of them, and with the current delayed (500 records, 1 %
noise) 9 % at 1 ms, 44 % at 2 ms, 92 % at 5 ms and 98 % at 10 ms (1 ms early: 22 %). The best shift lies within 4
samples of the true delay on 72 % of the delayed records, so the record is refused, not corrected: moved back by the
scan's shift, clean records read right on 58 % instead of 91 % (an answer needs its timing within about 2 samples).
The ratio a pipeline's clean records reach is its own: the 270 V rudder's paper-scale pipeline (30 samples, 22 modes)
explains 5 % of its clean records 1.8 x better at a far shift (ratios up to 7.9; 41 of those 50 answers wrong), and
its answers hardly depend on 0.5-2 ms of timing (74 of 125 right at 0.5 ms late, 68 % clean). So the check fires only
for a pipeline with its own threshold (metadata ``timing_ratio_max``): phm-evaluate calibrates it on held-out records
(:func:`calibrate_timing_ratio`: the ``TIMING_QUANTILE`` of their ratios, never below ``TIMING_RATIO``),
``scripts/add_timing_check.py`` gives it to a pipeline exported before, the shipped one among them; without it the
check is skipped and listed in ``checks_skipped``.

Below that threshold a record is answered, and where its best shift lies beyond the timing tolerance
(:mod:`.timing_tolerance`) its k intervals hold the readings around that shift too (:meth:`TimingScan.widens`),
whatever the ratio: the shift that explains the record best is a timing the data allow. On the pretrained pipeline, of
500 val-like records 2 ms late 274 -> 65 wrong and unflagged (222 refused either way), 5 ms 38 -> 12; of the 4,000
clean records about 9 % are widened so (median interval width 0.119 -> 0.121), 188 -> 187 wrong. Widening only
above a calibrated ratio (the 0.95 quantile of the held-out records', 1.31) left 92 of the 2 ms records wrong: most
late records read wrong are explained only 1.05-1.3 times better at their true timing.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import torch

from .command_check import shifted
from .noise_threshold import conformal_quantile

TIMING_RATIO = 1.8  # the least threshold: the 4,000 clean records reach 1.93 at a far shift (2 above 1.8)
MIN_SHIFT_S = 3e-4  # [s] nearer, a best shift is the answer's own jitter (72 % of clean records' within 0.2 ms)
MAX_SHIFT_SHARE = 0.025  # the scan covers +- this share of the record (12.5 ms of the reference's 0.5 s)
SCAN_POINTS = 5000  # the scan's step: the record's samples over this (2 samples of the reference's 10,001)
# The scan reads every COARSE-th step first, then every step around its REFINE lowest points: the statistic's minimum
# is smooth over a few samples (4 samples off it: 1.0-1.4 x its value). On 308 records of the pretrained pipeline
# (clean, 0.5-5 ms late, 1 ms early) this read 71 shifts instead of 251 and found the step-by-step scan's best shift
# on 307; the other, a clean record, is best 4 samples off (too near to fire) and read best at ratio 1.17 instead of
# 1.19, far below any threshold. scripts/bench_diagnose.py measures the scan's cost.
COARSE = 5
REFINE = 4
CHUNK = 64  # shifted records per consistency call (larger batches cost more per record on 2 cores)
# a pipeline's own threshold: this quantile of its held-out records' ratios (the 4,000 clean records above: 1.76 at
# 0.997, 1.63 at 0.99; the 270 V rudder's paper-scale pipeline, 1,000 clean records: 7.6 at 0.99)
TIMING_QUANTILE = 0.995
# Below that threshold a record is answered; where the scan's best shift lies beyond the timing tolerance
# (timing_tolerance.py), its k intervals hold the readings around it too (TimingScan.widens)
WIDEN_STEPS = 2  # the readings around the best shift: +- this many steps of the scan's grid (its own jitter)


@dataclass(frozen=True)
class TimingScan:
    """Outcome of :func:`timing_scan` for one record.

    Attributes:
        shift: the best shift [samples] (positive: the current lags the pipeline's grid, read ``x[i + shift]``).
        ratio: the consistency statistic unshifted over its value at the best shift (>= 1).
        statistic: the statistic unshifted (the ``inconsistent`` check's, > 1 flags).
        best: the statistic at the best shift.
    """

    shift: int
    ratio: float
    statistic: float
    best: float

    def lag_s(self, sample_rate: float) -> float:
        """The best shift in seconds at ``sample_rate`` [Hz]."""
        return self.shift / sample_rate

    def off(self, sample_rate: float, threshold: float = TIMING_RATIO) -> bool:
        """Whether the check fires: the best shift ``MIN_SHIFT_S`` or more away (and 2 samples at least), the
        record explained ``threshold`` times better there, and consistent with the answer as it came (statistic <= 1).
        A record inconsistent as it came is refused ``inconsistent`` already, and its best shift need not be its
        timing: the pretrained pipeline explains a current x2 best 2.1 ms late, and a shorted phase's record x1.5
        1.8 ms late, 3.7 x better."""
        far = abs(self.shift) >= max(2, math.ceil(MIN_SHIFT_S * sample_rate))
        return bool(far and self.ratio >= threshold and self.statistic <= 1.0)

    def widens(self, sample_rate: float, tolerance_s: float) -> bool:
        """Whether a record the check did not refuse must have its k intervals hold the readings around the best
        shift too: it lies beyond ``tolerance_s`` [s] (> 0), and the record is consistent with the answer as it came
        (otherwise the best shift need not be its timing, :meth:`off`)."""
        if tolerance_s <= 0 or abs(self.shift) <= tolerance_s * sample_rate + 1e-9:
            return False
        return bool(self.statistic <= 1.0)

    def message(self, sample_rate: float) -> str:
        """One line for the user on a record the check refuses."""
        lag = 1000.0 * self.lag_s(sample_rate)
        way = f"lag the pipeline's time grid by {lag:.2f} ms" if lag > 0 else f"lead it by {-lag:.2f} ms"
        return (
            f"the current is explained {self.ratio:.2f} x better by the pipeline's own answer moved in time: it seems "
            f"to {way} (a trigger offset, a logger's or filter's delay). The FDI reads timing to the sample, so the "
            "answer is withheld: record the command column with the current (a trigger offset is then corrected), "
            "or align the record and read it again"
        )


def can_scan(model: Any, n: int) -> bool:
    """Whether ``model`` (a loaded pipeline) has a consistency check to scan with, for a full record of ``n``
    samples."""
    return bool(getattr(model, "has_consistency", False)) and n == int(getattr(model, "n_full", -1))


def scan_shifts(n: int) -> list[int]:
    """The shifts [samples] the scan may read for a record of ``n`` samples: every ``n // SCAN_POINTS``-th within
    +- ``MAX_SHIFT_SHARE`` x n, 0 included."""
    step = max(1, n // SCAN_POINTS)
    reach = int(MAX_SHIFT_SHARE * n) // step * step
    return list(range(-reach, reach + 1, step))


def around(n: int, shift: int) -> list[int]:
    """The scan's shifts [samples] within ``WIDEN_STEPS`` steps of ``shift`` for a record of ``n`` samples."""
    grid = scan_shifts(n)
    step = grid[1] - grid[0] if len(grid) > 1 else 1
    return sorted({shift + j * step for j in range(-WIDEN_STEPS, WIDEN_STEPS + 1)} & set(grid))


def _statistics(model: Any, x: torch.Tensor, shifts: list[int], noise: float) -> torch.Tensor:
    """The consistency statistic (len(shifts),) float64 of the record ``x`` (n,) read at each shift."""
    dtype = model.times.dtype
    stats = []
    for start in range(0, len(shifts), CHUNK):
        block = torch.stack([shifted(x, s) for s in shifts[start : start + CHUNK]]).to(dtype)
        if math.isnan(noise):
            stats.append(model.consistency(block))
        else:
            stats.append(model.consistency(block, torch.full((block.shape[0],), noise, dtype=dtype)))
    return torch.cat(stats).double()


@torch.no_grad()
def timing_scan(model: Any, current: torch.Tensor, noise: float) -> TimingScan | None:
    """The scan of one full record ``current`` (n_full,) [A] as the pipeline reads it (after any rebase), at its
    estimated relative ``noise`` (NaN: each shifted record's own); None where the pipeline has no consistency
    check or the statistic is not finite unshifted. Coarse to fine: every ``COARSE``-th shift of
    :func:`scan_shifts`, then every one around the ``REFINE`` lowest."""
    n = current.numel()
    if not can_scan(model, n):
        return None
    grid = scan_shifts(n)
    step = grid[1] - grid[0] if len(grid) > 1 else 1
    x = current.double().flatten()
    coarse = [s for s in grid if (s // step) % COARSE == 0]
    stat = dict(zip(coarse, _statistics(model, x, coarse, noise).tolist()))
    at_zero = stat[0]
    finite = {s: v for s, v in stat.items() if math.isfinite(v)}
    if not math.isfinite(at_zero) or not finite:
        return None
    lowest = sorted(finite, key=finite.get)[:REFINE]
    near = sorted(({s + j * step for s in lowest for j in range(1 - COARSE, COARSE)} - set(stat)) & set(grid))
    if near:
        stat.update(zip(near, _statistics(model, x, near, noise).tolist()))
    best = min((s for s, v in stat.items() if math.isfinite(v)), key=stat.get)
    least = stat[best]
    ratio = at_zero / least if least > 0 else (1.0 if at_zero == 0 else math.inf)
    return TimingScan(best, max(1.0, ratio), at_zero, least)


def calibrate_timing_ratio(
    pipeline: Any, signals: torch.Tensor, sample_rate: float, quantile: float = TIMING_QUANTILE
) -> float | None:
    """The check's threshold for a pipeline from held-out records (B, n_full) [A] on time, with their noise: the
    split-conformal ``quantile`` of their ratios (1 for a record whose best shift lies too near to fire), never
    below ``TIMING_RATIO`` (a pipeline's own records may only loosen it). None: no consistency check to scan with,
    or no record."""
    if signals.shape[0] == 0 or not can_scan(pipeline, signals.shape[1]):
        return None
    with torch.no_grad():
        noise = pipeline.noise_level(signals.to(pipeline.times.dtype))
    ratios = []
    for record, level in zip(signals, noise.tolist()):
        scan = timing_scan(pipeline, record, level)
        if scan is not None:
            ratios.append(scan.ratio if scan.off(sample_rate, threshold=1.0) else 1.0)
    if not ratios:
        return None
    return max(TIMING_RATIO, conformal_quantile(torch.tensor(ratios, dtype=torch.float64), quantile))
