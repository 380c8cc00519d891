"""A logger's clock off by a relative error (phm_torch/online/clock_alignment.py): the stretch read off the record's
own command column and undone on every channel, with or without a trigger offset; a record on the right clock, one
without a command column and a command the windows cannot read are left as they came."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from phm_torch.command import Chirp, Profile, Sine
from phm_torch.online.clock_alignment import CLOCK_MIN, align_clock, stretched
from phm_torch.online.corruptions import Record
from phm_torch.online.record_corrections import align_trigger

RATE = 20000.0
CHIRP = Chirp(amplitude=5e-3, f_start=0.0, f_end=15.0, duration=0.5)
# profiles that hold still in most of the record's windows: a doublet of steps, a trapezoid of ramps and holds
DOUBLET = Profile([0.0, 0.02, 0.02, 0.18, 0.18, 0.34, 0.34, 0.5], [0.0, 0.0, 4e-3, 4e-3, -4e-3, -4e-3, 0.0, 0.0], 0.5)
TRAPEZOID = Profile([0.0, 0.05, 0.15, 0.3, 0.4, 0.5], [0.0, 0.0, 4e-3, 4e-3, 0.0, 0.0], 0.5)


def _record(command, error: float = 0.0, delay: int = 0) -> Record:
    """The test command's record (a current that follows it) written by a clock off by ``error`` and triggered
    ``delay`` samples late; the part the logger saw beyond the test's end holds its last value."""
    t = torch.arange(10001, dtype=torch.float64) / RATE
    seen = ((t * (1.0 + error)) - delay / RATE).clamp(min=0.0, max=float(t[-1]))
    cmd = command(seen)
    current = 0.2 + 40.0 * command(seen) + 0.1 * torch.sin(2 * math.pi * 3.0 * seen)
    return Record(t, cmd, 0.9 * cmd, current)


@pytest.mark.parametrize("error", [0.003, 0.005, -0.005, 0.01, -0.02])
def test_the_stretch_is_read_off_the_command_column_and_undone(error):
    truth = _record(CHIRP)
    record, found = align_clock(_record(CHIRP, error), CHIRP)
    assert found == pytest.approx(error, abs=2e-4)
    n = int(torch.isfinite(record.current).int().cumprod(0).sum())
    assert n >= 10001 * (1 - abs(error)) - 2  # a slower clock's record misses its end (NaN), nothing else
    span = float(truth.current.max() - truth.current.min())
    assert float((record.current[:n] - truth.current[:n]).abs().max()) < 2e-3 * span
    assert torch.equal(torch.isfinite(record.position), torch.isfinite(record.current))  # every channel alike


@pytest.mark.parametrize("command", [DOUBLET, TRAPEZOID], ids=["doublet", "trapezoid"])
@pytest.mark.parametrize("error", [0.002, 0.005, -0.005, 0.01, -0.02])
def test_a_profile_that_holds_still_is_read_where_it_moves(command, error):
    """Before, the windows of the record's second half held still (the doublet's last step at 0.34 s, the
    trapezoid's hold) and no stretch was found: the record went on stretched, its k_hat moved and nothing was
    flagged. Now the windows where the command moves give it, refined on the command column's own fit."""
    truth = _record(command)
    record, found = align_clock(_record(command, error), command)
    assert found == pytest.approx(error, abs=2e-4)
    n = int(torch.isfinite(record.current).int().cumprod(0).sum())
    span = float(truth.current.max() - truth.current.min())
    # a step lands within a sample of its place; elsewhere the channels are undone
    wrong = (record.current[:n] - truth.current[:n]).abs() > 2e-2 * span
    assert int(wrong.sum()) <= 6
    assert align_clock(_record(command), command)[1] == 0.0  # the right clock: left as it came


def test_with_a_trigger_offset_the_stretch_then_the_shift():
    record, found = align_clock(_record(CHIRP, 0.004, delay=60), CHIRP)
    assert found == pytest.approx(0.004, abs=2e-4)
    aligned, lag = align_trigger(record, CHIRP)
    assert lag == pytest.approx(60 / RATE, abs=2 / RATE)
    truth = _record(CHIRP)
    seen = torch.isfinite(aligned.current)
    span = float(truth.current.max() - truth.current.min())
    assert float((aligned.current[seen] - truth.current[seen]).abs().max()) < 5e-3 * span


def test_what_is_left_as_it_came():
    assert align_clock(_record(CHIRP), CHIRP)[1] == 0.0  # the right clock
    assert align_clock(_record(CHIRP, 0.5 * CLOCK_MIN), CHIRP)[1] == 0.0  # too small to move an answer
    rec = _record(CHIRP, 0.005)
    assert align_clock(Record(rec.time, None, None, rec.current), CHIRP)[1] is None  # no command column
    assert align_clock(rec, None)[1] is None  # no test command
    sine = Sine(amplitude=5e-3, frequency=40.0, duration=0.5)  # 25 samples a period: the windows alias
    _, found = align_clock(_record(sine, 0.01), sine)
    assert found == 0.0 or found == pytest.approx(0.01, abs=2e-4)  # never a wrong stretch


def test_stretched_is_the_inverse_of_a_clock_error():
    x = torch.as_tensor(np.sin(np.linspace(0.0, 20.0, 2001)))
    assert stretched(x, 0.0) is x and stretched(None, 0.01) is None
    fast = torch.as_tensor(np.interp(np.arange(2001) * 1.01, np.arange(2001), x.numpy(), right=np.nan))
    back = stretched(fast, 0.01)
    assert float((back[:1900] - x[:1900]).abs().max()) < 1e-3
