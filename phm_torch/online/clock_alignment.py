"""A logger whose clock runs fast or slow: every channel of the record stretched against the test command.

A record written by a logger with a clock off by a relative error e holds at its sample time tau what happened at
t = (1 + e) tau: over the 0.5 s chirp, 0.5 % puts its end 2.5 ms off. The command check did not see it (NRMSE 0.03,
under its tolerance), the trigger alignment cannot undo it (no single shift fits), and the FDI read the stretched
current as faults: 3 of the corruption suite's 4 records wrong at +0.5 %, 4 of 4 at -0.5 %, nothing flagged.

The record's own command column tells the stretch, as it tells a trigger offset (:func:`~.record_corrections.align_trigger`):
:func:`align_clock` finds the command column's shift against the test command in ``WINDOWS`` windows of the record's
second half (where a chirp is fastest, so a shift is sharpest; for a command that holds still in some of them, a
profile of steps and holds, in every window of the record where it moves: :func:`window_starts`), fits shift = a - e tau by least squares, and where
|e| is at least ``CLOCK_MIN`` resamples every channel by it (linear interpolation; the part of the test command's
grid the record never saw is missing, NaN); the trigger alignment then moves the record by its shift. The stretch
is kept only where the command column, stretched and best shifted, matches the test command within the command
check's tolerance and at most half as far off as the record as it came (a periodic command whose windows alias
fails this and is left as it came).
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import torch
from scipy.optimize import minimize_scalar

from .command_check import NRMSE_TOLERANCE, command_lag, command_nrmse, lag_limit, lag_residuals, shifted
from .corruptions import Record

CLOCK_MAX = 0.025  # the largest relative clock error corrected (a window's shift is searched up to a quarter of it)
CLOCK_MIN = 0.001  # a smaller one is left alone (0.2 % left the suite's answers right)
WINDOWS = 4  # windows of the record's second half whose shifts give the stretch
OUTLIER_SAMPLES = 2.0  # a window whose shift misses the others' line by more is left out (then the fit is redone)
ACTIVE_SHARE = 0.1  # a window where the command spreads less than this share of its busiest window's tells no shift


def stretched(x: torch.Tensor | None, error: float) -> torch.Tensor | None:
    """A channel (n,) recorded by a clock off by ``error`` (relative), resampled onto the true time grid: the sample
    at true time t_j is the record's at t_j / (1 + error), linearly interpolated; NaN beyond the record's span."""
    if x is None or error == 0.0:
        return x
    n = x.numel()
    at = np.arange(n, dtype=np.float64) / (1.0 + error)  # in the record's samples
    values = x.double().numpy()
    out = np.interp(at, np.arange(n, dtype=np.float64), values, right=np.nan)
    return torch.as_tensor(out, dtype=x.dtype)


def _miss(cmd: torch.Tensor, expected: torch.Tensor, error: float, max_lag: int) -> float:
    """The command column's NRMSE against the test command once resampled for ``error`` and best shifted, over the
    samples the resampled record has (its leading run: a record read by a slower clock misses its end)."""
    c = stretched(cmd, error)
    m = int(torch.isfinite(c).int().cumprod(0).sum())
    lag = command_lag(c[:m], expected[:m], max_lag)
    return command_nrmse(shifted(c[:m].double(), lag), expected[:m])


def window_shift(recorded: torch.Tensor, expected: torch.Tensor, max_lag: int) -> float:
    """The shift [samples] of a window of the command column against the test command, to a fraction of a sample:
    :func:`~.command_check.command_lag`'s least squares, its minimum refined by the parabola through its neighbours
    (whole samples left the fitted stretch up to 1e-3 off over the chirp's second half)."""
    lags, residual = lag_residuals(recorded, expected, max_lag)
    i = int(torch.argmin(residual))
    if 0 < i < residual.numel() - 1:
        left, mid, right = (float(residual[j]) for j in (i - 1, i, i + 1))
        curvature = left - 2.0 * mid + right
        if curvature > 0:
            return float(lags[i]) + 0.5 * (left - right) / curvature
    return float(lags[i])


def window_starts(expected: torch.Tensor, n: int) -> tuple[list[int], int, bool]:
    """Where the stretch is read: the starts of ``WINDOWS`` windows of the record's second half (where a chirp is
    fastest, so a shift is sharpest) when the test command moves in each of them; otherwise (a profile of steps and
    holds, a command that settles early) every one of the record's ``2 WINDOWS`` windows in which it moves by at least
    ``ACTIVE_SHARE`` of its busiest window's spread: a window where the command holds still tells no shift. Returns
    (starts, width) [samples] and whether the windows are the second half's (False: the command holds still in some).
    """
    width = n // (2 * WINDOWS)
    spread = [float(expected[k * width : (k + 1) * width].std()) for k in range(2 * WINDOWS)]
    active = [k * width for k, v in enumerate(spread) if v > 0 and v >= ACTIVE_SHARE * max(spread)]
    second_half = [n - (WINDOWS - k) * width for k in range(WINDOWS)]
    if all(float(expected[s : s + width].std()) >= ACTIVE_SHARE * max(spread) > 0 for s in second_half):
        return second_half, width, True
    return active, width, False


def _window_fit(cmd: torch.Tensor, expected: torch.Tensor, n: int) -> float:
    """The relative clock error e of shift = a - e tau fitted by least squares to the command column's shifts in the
    windows of :func:`window_starts` (a window the record does not fill is left out)."""
    starts, width, _ = window_starts(expected, n)
    starts = [s for s in starts if bool(torch.isfinite(cmd[s : s + width]).all())]
    if len(starts) < 2:
        return 0.0
    shifts = np.array([window_shift(cmd[s : s + width], expected[s : s + width], width // 4) for s in starts])
    centres = np.array([s + width / 2.0 for s in starts])
    keep = np.ones(len(starts), dtype=bool)
    while True:  # a window that holds still but for the start of a ramp can read a shift at its search's bound
        design = np.stack([np.ones(int(keep.sum())), centres[keep]], 1)
        fit = np.linalg.lstsq(design, shifts[keep], rcond=None)[0]
        off = np.where(keep, np.abs(shifts - fit[0] - fit[1] * centres), -1.0)
        if keep.sum() <= 2 or off.max() <= OUTLIER_SAMPLES:
            return -float(fit[1])
        keep[int(np.argmax(off))] = False


def align_clock(record: Record, command: Callable[[torch.Tensor], torch.Tensor] | None) -> tuple[Record, float | None]:
    """The record resampled onto the test command's clock, and the relative clock error it needed (None: no command
    column or no test command to compare with; 0.0: none found or none needed)."""
    cmd = record.command
    n = 0 if cmd is None else cmd.numel()
    if command is None or n < 8 * WINDOWS or not bool(torch.isfinite(cmd).all()):
        return record, None
    t = (record.time - record.time[0]).double()
    expected = command(t)
    error = _window_fit(cmd, expected, n)
    if CLOCK_MIN <= abs(error) <= CLOCK_MAX:  # a second pass on the record so stretched: a window's own stretch
        residual = _window_fit(stretched(cmd, error), expected, n)  # biased the first (5 % of it at 2 %)
        error = (1.0 + error) * (1.0 + residual) - 1.0
    rate = (n - 1) / float(t[-1])
    lags = lag_limit(n, rate)
    if not window_starts(expected, n)[2] and 0.5 * CLOCK_MIN <= abs(error) <= 2.0 * CLOCK_MAX:
        error = _refined(cmd, expected, error, lags)
    if not CLOCK_MIN <= abs(error) <= CLOCK_MAX:
        return record, 0.0
    before, after = _miss(cmd, expected, 0.0, lags), _miss(cmd, expected, error, lags)
    if not (after <= NRMSE_TOLERANCE and after <= 0.5 * before):
        return record, 0.0
    channels = (stretched(c, error) for c in (record.command, record.position, record.current))
    return Record(record.time, *channels), error


def _refined(cmd: torch.Tensor, expected: torch.Tensor, error: float, max_lag: int) -> float:
    """The clock error near ``error`` that brings the command column closest to the test command (:func:`_miss`,
    bounded scalar minimisation: ~20 resamplings, 0.2 s a record). Only for a command that holds still in some
    windows: there a window's shift is read off a few steps or ramp ends (a ramp's window read 8 % of the stretch
    short), while a sweep's windows read it within 2e-4."""
    half = max(0.5 * abs(error), CLOCK_MIN)
    found = minimize_scalar(
        lambda e: _miss(cmd, expected, float(e), max_lag),
        bounds=(error - half, error + half),
        method="bounded",
        options={"xatol": 1e-5},
    )
    return float(found.x)
