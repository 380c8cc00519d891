"""Input contract of the online pipeline: is a record's ``command`` column the pipeline's test command?

A pipeline knows only the records of its own test command. A record taken with another command (another
amplitude or frequency range), or shifted against it (a trigger offset), gives a current that the FDI maps
onto confident but wrong fault estimates, so the command is checked before the answer is trusted.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

NRMSE_TOLERANCE = 0.05  # RMS of (recorded - expected command) over the expected command's range
MAX_LAG_S = 0.05  # the trigger offsets searched [s] (a tenth of the reference's 0.5 s record) ...
MAX_LAG_SHARE = 0.1  # ... or this share of a longer record (a 5 s test command: 0.5 s)


def unit_hint(column: str, gain: float) -> str:
    """A hint when a recorded ``column`` (``command`` or ``position``) is ``gain`` x what the pipeline expects and
    that is a unit's factor: degrees (57.3 x), mrad or, on a linear actuator, mm (1000 x); else ``""``."""
    for unit, factor in (("deg", 180.0 / math.pi), ("mrad", 1000.0)):
        if 0.8 * factor <= gain <= 1.25 * factor:
            other = " (or mm on a linear actuator: '[mm]')" if unit == "mrad" else ""
            return f" (the {column} written in {unit}? name the column '{column} [{unit}]'{other})"
    return ""


def lag_limit(n_samples: int, sample_rate: float) -> int:
    """The largest trigger offset [samples] the command check and the record corrections search, for a record of
    ``n_samples`` at ``sample_rate`` [Hz]: ``MAX_LAG_S`` or ``MAX_LAG_SHARE`` of the record, the longer."""
    return round(max(MAX_LAG_S, MAX_LAG_SHARE * (n_samples - 1) / sample_rate) * sample_rate)


@dataclass(frozen=True)
class CommandCheck:
    """Outcome of :func:`check_command`.

    Attributes:
        nrmse: RMS difference between the recorded and the expected command over the expected one's range.
        best_lag_s: the shift [s] of the recorded command that matches the expected one best (positive: the
            record starts late), within +- :func:`lag_limit`.
        gain: least-squares gain of the recorded command on the expected one at that lag (1: same size).
        ok: ``nrmse <= tolerance``.
    """

    nrmse: float
    best_lag_s: float
    gain: float
    ok: bool

    def reason(self) -> str:
        """One line for the user, e.g. ``command differs from the pipeline's test command: NRMSE 0.31, ...``."""
        return (
            f"command differs from the pipeline's test command: NRMSE {self.nrmse:.2f}, best lag "
            f"{1000 * self.best_lag_s:.1f} ms, gain {self.gain:.2f}{unit_hint('command', self.gain)}"
        )


def check_command(
    recorded: torch.Tensor, expected: torch.Tensor, sample_rate: float, tolerance: float = NRMSE_TOLERANCE
) -> CommandCheck:
    """Compare a record's command column with the pipeline's test command on the same time grid.

    Args:
        recorded: (n,) the record's command [rad].  expected: (n,) the test command at the record's times.
        sample_rate: [Hz], to express the lag in seconds.  tolerance: the largest NRMSE accepted.

    Raises:
        ValueError: shapes differ, or the expected command is constant (nothing to compare with).
    """
    recorded, expected = recorded.double().flatten(), expected.double().flatten()
    if recorded.shape != expected.shape:
        raise ValueError(f"command: the record has {recorded.numel()} samples, the test command {expected.numel()}")
    span = float(expected.max() - expected.min())
    if not span > 0:
        raise ValueError("command: the pipeline's test command is constant; nothing to check the record against")
    nrmse = command_nrmse(recorded, expected)
    if nrmse <= tolerance:  # the search below only explains a mismatch
        gain = float((recorded * expected).sum() / expected.pow(2).sum())
        return CommandCheck(nrmse, 0.0, gain, True)
    n = recorded.numel()
    lag = command_lag(recorded, expected, lag_limit(n, sample_rate))  # recorded[i] = expected[i - lag]
    r, e = recorded[max(lag, 0) : n + min(lag, 0)], expected[max(-lag, 0) : n - max(lag, 0)]
    gain = float((r * e).sum() / e.pow(2).sum().clamp_min(1e-300))
    return CommandCheck(nrmse, lag / sample_rate, gain, False)


def command_nrmse(recorded: torch.Tensor, expected: torch.Tensor) -> float:
    """RMS of (recorded - expected) over the expected command's range, on their finite samples: the command
    check's measure of how far a record's command column is from the test command."""
    recorded, expected = recorded.double().flatten(), expected.double().flatten()
    seen = torch.isfinite(recorded) & torch.isfinite(expected)
    span = float(expected[seen].max() - expected[seen].min())
    return float((recorded[seen] - expected[seen]).pow(2).mean().sqrt()) / span


def command_lag(recorded: torch.Tensor, expected: torch.Tensor, max_lag: int) -> int:
    """The shift (samples, |lag| <= ``max_lag``) with ``recorded[i] ~ g expected[i - lag]`` in least squares over
    the overlap (any gain g), found for every lag at once by FFT correlation: positive when the record lags the
    test command (its acquisition triggered early or its clock started late).

    Args:
        recorded: (n,) the record's command column [rad].  expected: (n,) the test command at the record's times.
        max_lag: the largest shift searched, in samples (>= 0).
    """
    lags, residual = lag_residuals(recorded, expected, max_lag)
    return int(lags[int(torch.argmin(residual))])


def lag_residuals(recorded: torch.Tensor, expected: torch.Tensor, max_lag: int) -> tuple[torch.Tensor, torch.Tensor]:
    """(lags (L,), mean squared residual (L,)) of :func:`command_lag`'s least squares at every shift it searches."""
    r, e = recorded.double().flatten(), expected.double().flatten()
    n = r.numel()
    max_lag = max(0, min(int(max_lag), n // 4))
    size = 1 << (2 * n - 1).bit_length()
    corr = torch.fft.irfft(torch.fft.rfft(r, size) * torch.fft.rfft(e, size).conj(), size)
    lags = torch.arange(-max_lag, max_lag + 1)
    cross = corr[lags % size]  # sum_i r[i] e[i - lag]
    r2 = torch.cat([torch.zeros(1, dtype=r.dtype), torch.cumsum(r * r, 0)])
    e2 = torch.cat([torch.zeros(1, dtype=e.dtype), torch.cumsum(e * e, 0)])
    start, stop = lags.clamp(min=0), n + lags.clamp(max=0)  # the overlap, in the record's samples
    r_energy = r2[stop] - r2[start]
    e_energy = e2[stop - lags] - e2[start - lags]
    return lags, (r_energy - cross.pow(2) / e_energy.clamp_min(1e-300)) / (stop - start)


def shifted(x: torch.Tensor | None, lag: int) -> torch.Tensor | None:
    """``x[i + lag]`` (n,) with NaN where that falls outside the record: a record lagging the test command by
    ``lag`` samples (:func:`command_lag`) moved back onto its time grid, its unseen part missing."""
    if x is None or lag == 0:
        return x
    out = torch.full_like(x, float("nan"))
    n = x.numel()
    if abs(lag) < n:
        if lag > 0:
            out[: n - lag] = x[lag:]
        else:
            out[-lag:] = x[: n + lag]
    return out
