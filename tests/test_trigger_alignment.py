"""Trigger offsets: the record's own command column gives its shift against the test command
(``command_check.command_lag``, every lag at once by FFT, exact least squares), and ``record_corrections.align_trigger`` moves
every channel back onto the test command's grid, its unseen end missing; another command is left alone."""

from __future__ import annotations

import math

import torch

from phm_torch.command import Chirp
from phm_torch.online.command_check import command_lag, shifted
from phm_torch.online.corruptions import Record
from phm_torch.online.record_corrections import align_trigger

RATE = 20000.0
T = torch.arange(10001, dtype=torch.float64) / RATE
CHIRP = Chirp()


def _delayed(x: torch.Tensor, lag: int) -> torch.Tensor:
    """x[i - lag] (the record lags by ``lag`` samples), the end value held outside."""
    if lag >= 0:
        return torch.cat([x[:1].expand(lag), x[: x.numel() - lag]])
    return torch.cat([x[-lag:], x[-1:].expand(-lag)])


def _exhaustive_lag(r: torch.Tensor, e: torch.Tensor, max_lag: int) -> int:
    """The same least-squares criterion, one lag at a time."""
    n, best = r.numel(), (math.inf, 0)
    for lag in range(-max_lag, max_lag + 1):
        a, b = r[max(lag, 0) : n + min(lag, 0)], e[max(-lag, 0) : n - max(lag, 0)]
        g = (a * b).sum() / (b * b).sum()
        err = float((a - g * b).pow(2).mean())
        if err < best[0]:
            best = (err, lag)
    return best[1]


def test_command_lag_finds_the_shift_of_a_noisy_command_and_equals_the_exhaustive_search():
    expected = CHIRP(T)
    gen = torch.Generator().manual_seed(0)
    for lag in (0, 1, 7, 40, 400, -3, -250):
        recorded = 1.02 * _delayed(expected, lag) + 2e-5 * torch.randn(T.numel(), generator=gen, dtype=T.dtype)
        assert command_lag(recorded, expected, 1000) == lag
    recorded = _delayed(expected, 13) + 1e-3 * torch.randn(T.numel(), generator=gen, dtype=T.dtype)
    assert command_lag(recorded[:3001], expected[:3001], 60) == _exhaustive_lag(recorded[:3001], expected[:3001], 60)


def test_shifted_moves_samples_and_marks_the_unseen_part_missing():
    x = torch.arange(6, dtype=torch.float64)
    y = shifted(x, 2)
    assert y[:4].tolist() == [2.0, 3.0, 4.0, 5.0] and torch.isnan(y[4:]).all()
    y = shifted(x, -1)
    assert torch.isnan(y[0]) and y[1:].tolist() == [0.0, 1.0, 2.0, 3.0, 4.0]
    assert shifted(x, 0) is x and shifted(None, 3) is None and torch.isnan(shifted(x, 9)).all()


def test_align_trigger_restores_every_channel_and_leaves_other_commands_alone():
    command = CHIRP(T)
    current = 1.0 + torch.sin(2 * math.pi * 37 * T)
    position = 0.97 * command
    lag = 60  # 3 ms
    late = Record(T, _delayed(command, lag), _delayed(position, lag), _delayed(current, lag))
    aligned, offset = align_trigger(late, CHIRP)
    assert offset == lag / RATE
    n = T.numel() - lag
    for got, want in ((aligned.command, command), (aligned.position, position), (aligned.current, current)):
        torch.testing.assert_close(got[:n], want[:n])
        assert torch.isnan(got[n:]).all()
    on_time = Record(T, command, position, current)
    assert align_trigger(on_time, CHIRP) == (on_time, 0.0)
    assert align_trigger(Record(T, None, None, current), CHIRP) == (Record(T, None, None, current), None)
    # the command column shifted alone (another logger): its position leads it, so nothing is moved
    assert align_trigger(Record(T, _delayed(command, lag), position, current), CHIRP)[1] == 0.0
    # another command (twice the chirp rate) is no trigger offset: left for the command check to refuse
    other = Record(T, Chirp(f_end=30.0)(T), position, current)
    assert align_trigger(other, CHIRP)[1] == 0.0


def test_a_long_test_command_is_searched_over_a_tenth_of_its_record():
    """A 5 s chirp at 2 kHz recorded 0.2 s late is realigned: the search reaches 0.05 s or a tenth of the record,
    the longer (0.5 s here; 0.05 s on the reference's 0.5 s record, as before)."""
    from phm_torch.online.command_check import lag_limit

    assert lag_limit(10001, 20000.0) == 1000 and lag_limit(10001, 2000.0) == 1000
    rate = 2000.0
    t = torch.arange(10001, dtype=torch.float64) / rate
    chirp = Chirp(amplitude=0.01, f_end=2.0, duration=5.0)
    command = chirp(t)
    current = 1.0 + torch.sin(2 * math.pi * 3 * t)
    lag = 400  # 0.2 s
    late = Record(t, _delayed(command, lag), _delayed(0.97 * command, lag), _delayed(current, lag))
    aligned, offset = align_trigger(late, chirp)
    assert offset == lag / rate
    torch.testing.assert_close(aligned.current[: t.numel() - lag], current[: t.numel() - lag])
