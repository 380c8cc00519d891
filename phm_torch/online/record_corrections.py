"""What is corrected in a record before the online pipeline reads it, where the record itself shows the fault exactly.

A bench writes records with its own faults, which the FDI would read as the actuator's: a logger's clock running
fast or slow (:mod:`.clock_alignment`), a trigger offset, a current probe or a position sensor the wrong way round.
Each shows in the record itself (its command column, its sign against the nominal record), so each is undone rather
than refused, and said: :func:`prepare_record` applies them in that order and returns what it did
(:class:`Corrections`, whose :meth:`~Corrections.messages` phm-predict writes). The fleet check of phm-track reads the
first inspections through the same function, so that its mean record is the one the pipeline read.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import torch

from ..metrics import finite_mean
from .clock_alignment import align_clock
from .command_check import NRMSE_TOLERANCE, command_lag, command_nrmse, lag_limit, shifted
from .corruptions import Record, sample_rate
from .input_contract import REVERSED_CORRELATION, nominal_correlation


def align_trigger(
    record: Record, command: Callable[[torch.Tensor], torch.Tensor] | None
) -> tuple[Record, float | None]:
    """The record moved onto the test command's time grid, and the shift [s] it needed (None: no command column or
    no test command to align on; 0.0: already aligned).

    A trigger offset shifts every channel against the test command: the FDI then reads the current's timing as
    faults (0.5 ms moved err_k as much as a real fault and no check saw it). The record's own command column
    tells the shift (:func:`~.command_check.command_lag`); the shifted record's unseen end is missing (NaN),
    which the gappy layer and the checks handle. It is applied only when the shifted command matches the test
    command within the command check's tolerance and better than unshifted: another command is left for the
    command check to refuse."""
    cmd = record.command
    # the column's leading finite run (a record resampled onto a faster clock misses its end: clock_alignment.py)
    m = 0 if cmd is None else int(torch.isfinite(cmd).int().cumprod(0).sum())
    if cmd is None or command is None or m < max(4, cmd.numel() // 2) or bool(torch.isfinite(cmd[m:]).any()):
        return record, None
    t = (record.time - record.time[0]).double()
    rate = sample_rate(record.time)
    expected = command(t)
    lag = command_lag(cmd[:m], expected[:m], lag_limit(t.numel(), rate))
    if lag == 0:
        return record, 0.0
    before, after = command_nrmse(cmd, expected), command_nrmse(shifted(cmd.double(), lag), expected)
    if not (after <= NRMSE_TOLERANCE and after < before):
        return record, 0.0
    # one trigger moves every channel: the position still follows its command column, never leads it; a
    # command column shifted alone (another logger) is left for the command check to refuse
    position = record.position
    if (
        position is not None
        and bool(torch.isfinite(position[:m]).all())
        and command_lag(position[:m], cmd[:m], lag_limit(t.numel(), rate)) < 0
    ):
        return record, 0.0
    aligned = Record(record.time, shifted(cmd, lag), shifted(record.position, lag), shifted(record.current, lag))
    return aligned, lag / rate


# A current probe the wrong way round: the record's mean current has the other sign than the nominal record's (the
# envelope current of every fault vector keeps the nominal sign; the input contract's ``sign`` check) and its shape is
# anti-correlated with the nominal record's (the heaviest val-like faults still correlate at +0.22 or more).
CURRENT_REVERSED_CORRELATION = 0.0


def polarity_reversal(current: torch.Tensor, nominal: torch.Tensor | None) -> float | None:
    """The correlation (< ``CURRENT_REVERSED_CORRELATION``) with the nominal record (n_full,) [A] of a current (n_full,) [A]
    that a probe read the wrong way round, None where it is not reversed (or there is nothing to compare with).

    Read as it came, a reversed current was refused (``sign``, ``inconsistent``) and a bench with its probe turned
    round tracked nothing; its sign is unambiguous, so phm-predict and phm-track restore it like a trigger offset,
    and say so. A record whose mean has the other sign but whose shape still follows the nominal record is left for
    the ``sign`` check to refuse."""
    if nominal is None or current.shape != nominal.shape:
        return None
    x, nominal = current.double(), nominal.double()
    if not float(finite_mean(x)) * float(nominal.mean()) < 0:
        return None
    present = torch.isfinite(x)  # over the samples it has (the shape check fills the missing with the nominal's)
    corr = float(nominal_correlation(x[present], nominal[present])) if int(present.sum()) > 2 else 0.0
    return corr if corr < CURRENT_REVERSED_CORRELATION else None


def correct_polarity(record: Record, nominal: torch.Tensor | None) -> tuple[Record, float | None]:
    """The record with its current's sign restored where :func:`polarity_reversal` finds it reversed, and that
    correlation (None: left as it came)."""
    corr = polarity_reversal(record.current, nominal)
    if corr is None:
        return record, None
    return Record(record.time, record.command, record.position, -record.current), corr


def correct_position_polarity(record: Record) -> tuple[Record, float | None]:
    """The record with its position's sign restored where the position sensor reads the wrong way round, and the
    correlation with the command column that showed it (None: left as it came).

    A position anti-correlated with its command (below the tracking check's ``REVERSED_CORRELATION``) is a reversed
    sensor (a stalled actuator correlates near 0, the paper store's val records at 0.82 and above): read the other
    way round, it is checked as any position is (its tracking range); the FDI never reads it."""
    cmd, pos = record.command, record.position
    if cmd is None or pos is None:
        return record, None
    both = torch.isfinite(cmd) & torch.isfinite(pos)  # a record aligned on its trigger or clock misses its ends
    if int(both.sum()) < 3:
        return record, None
    corr = float(torch.corrcoef(torch.stack([pos[both].double(), cmd[both].double()]))[0, 1])
    if not corr < REVERSED_CORRELATION:  # NaN (a constant position or command) is not reversed
        return record, None
    return Record(record.time, record.command, -record.position, record.current), corr


@dataclass(frozen=True)
class Corrections:
    """What :func:`prepare_record` did: the relative clock error undone and the trigger offset [s] (None: no command
    column or test command to read them from; 0.0: none), the correlations that showed a reversed current or position
    (None: not reversed)."""

    clock_error: float | None
    trigger_offset_s: float | None
    current_correlation: float | None
    position_correlation: float | None

    def messages(self) -> list[str]:
        """One line for each correction made."""
        out = []
        if self.clock_error:
            out.append(
                f"the record's clock ran {100 * self.clock_error:+.2f} % off the test command's (from its command "
                "column): every channel was resampled onto the test command's time grid"
            )
        lag = self.trigger_offset_s
        if lag:
            out.append(
                f"the record lagged the test command by {1000 * lag:.2f} ms (a trigger offset): every channel "
                f"was moved back onto the test command's time grid, its last {1000 * abs(lag):.2f} ms missing"
                if lag > 0
                else f"the record led the test command by {-1000 * lag:.2f} ms (a trigger offset): every "
                f"channel was moved onto the test command's time grid, its first {-1000 * lag:.2f} ms missing"
            )
        if self.current_correlation is not None:
            out.append(
                f"the current read reversed (its mean of the other sign than the nominal record's, its correlation "
                f"with it {self.current_correlation:.2f}): a current probe the wrong way round; read as -current"
            )
        if self.position_correlation is not None:
            out.append(
                f"the position read reversed (correlation {self.position_correlation:.2f} with the command column): "
                "a position sensor the wrong way round; read as -position"
            )
        return out


def prepare_record(
    record: Record, command: Callable[[torch.Tensor], torch.Tensor] | None, nominal: torch.Tensor | None
) -> tuple[Record, Corrections]:
    """The record as the pipeline reads it (its clock, trigger and sensor signs corrected against the test
    ``command`` and the ``nominal`` record (n_full,) [A]), and what was corrected."""
    record, clock_error = align_clock(record, command)
    record, trigger_lag = align_trigger(record, command)
    record, current_corr = correct_polarity(record, nominal)
    record, position_corr = correct_position_polarity(record)
    return record, Corrections(clock_error, trigger_lag, current_corr, position_corr)
