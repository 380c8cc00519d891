"""Corruptions of a measured record, the ways a test bench spoils one: a registry for the corruption suite.

Each corruption is a pure function ``(time, command, position, current, severity, rng) -> Record`` of one
record (tensors (n,) on a uniform grid; ``command`` and ``position`` may be ``None``, a current-only record;
NaN in ``current`` is a missing sample) and a severity in the kind's own unit, which is relative to the record
(a fraction of its RMS current, of the command's range, a delay in seconds...) so that no actuator's values
are written here. ``CORRUPTIONS`` maps each kind's name to a :class:`Corruption` with its severities (increasing,
mildest first) and the unit; :func:`corrupt` applies one by name.

Kinds that need another simulation (another actuator's record, a wrong command amplitude or frequency) are
not record functions; :mod:`phm_torch.online.corruption_suite` simulates those.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import torch
from scipy.signal import lfilter

HUM_FREQUENCY = 400.0  # [Hz] the aircraft mains frequency (and its hum on a bench's probes)


@dataclass(frozen=True)
class Record:
    """One record: time [s], command [rad] and position [rad] (``None`` when absent), current [A]; each (n,)."""

    time: torch.Tensor
    command: torch.Tensor | None
    position: torch.Tensor | None
    current: torch.Tensor


CorruptionFn = Callable[
    [torch.Tensor, "torch.Tensor | None", "torch.Tensor | None", torch.Tensor, float, np.random.Generator], Record
]


@dataclass(frozen=True)
class Corruption:
    """A registered corruption: the function, its severities (mildest first), their unit, one line on it."""

    fn: CorruptionFn
    severities: tuple[float, ...]
    unit: str
    description: str


CORRUPTIONS: dict[str, Corruption] = {}


def register(
    name: str, severities: tuple[float, ...], unit: str, description: str
) -> Callable[[CorruptionFn], CorruptionFn]:
    """Decorator adding a corruption to ``CORRUPTIONS`` under ``name``."""

    def add(fn: CorruptionFn) -> CorruptionFn:
        if name in CORRUPTIONS:
            raise ValueError(f"corruption {name!r} is registered twice")
        CORRUPTIONS[name] = Corruption(fn, tuple(severities), unit, description)
        return fn

    return add


def corrupt(name: str, record: Record, severity: float, rng: np.random.Generator) -> Record:
    """``record`` spoilt by the corruption ``name`` at ``severity``."""
    if name not in CORRUPTIONS:
        raise ValueError(f"corruption: unknown kind {name!r}; available: {sorted(CORRUPTIONS)}")
    return CORRUPTIONS[name].fn(record.time, record.command, record.position, record.current, float(severity), rng)


def _rms(x: torch.Tensor) -> float:
    finite = x[torch.isfinite(x)]
    return float(finite.pow(2).mean().sqrt())


def sample_rate(time: torch.Tensor) -> float:
    """The sample rate [Hz] of a record's time column (n,) [s], from its first and last finite times (NaN for fewer
    than two or no span): every reader of a record's rate (the corruptions, the trigger alignment, the command check,
    the bench lines) takes it from here."""
    finite = time[torch.isfinite(time)]
    span = float(finite[-1] - finite[0]) if finite.numel() > 1 else math.nan
    return (time.numel() - 1) / span if span > 0 else math.nan


def delayed(x: torch.Tensor | None, samples: int) -> torch.Tensor | None:
    """x (n,) delayed by ``samples`` (> 0: starts late, its first value held before it; < 0: starts early, its last
    value held after it), as a recorder triggered off by that much writes it."""
    if x is None or samples == 0:
        return x
    if samples < 0:
        return torch.cat([x[-samples:], x[-1:].expand(-samples)])
    return torch.cat([x[:1].expand(samples), x[:-samples]])


def _burst(n: int, fraction: float, rng: np.random.Generator) -> slice:
    length = max(1, round(fraction * n))
    start = int(rng.integers(0, n - length + 1))
    return slice(start, start + length)


def _noise(n: int, rng: np.random.Generator, dtype: torch.dtype) -> torch.Tensor:
    return torch.as_tensor(rng.standard_normal(n), dtype=dtype)


@register("current_gain", (0.05, 0.1, 0.25, 0.5, 1.0), "gain error (current x (1 + s))", "probe range or scale error")
def current_gain(time, command, position, current, severity, rng):
    return Record(time, command, position, current * (1.0 + severity))


@register("current_offset", (0.05, 0.1, 0.25, 0.5), "offset / RMS current", "probe offset (zero not trimmed)")
def current_offset(time, command, position, current, severity, rng):
    return Record(time, command, position, current + severity * _rms(current))


@register("current_sign", (1.0,), "-", "probe the wrong way round")
def current_sign(time, command, position, current, severity, rng):
    return Record(time, command, position, -current)


@register("clipping", (0.05, 0.1, 0.2, 0.5), "fraction of the peak cut", "ADC or probe saturation")
def clipping(time, command, position, current, severity, rng):
    finite = current[torch.isfinite(current)]
    low, high = float(finite.min()), float(finite.max())
    return Record(time, command, position, current.clamp(max=high - severity * (high - low)))


@register("dropout_burst", (0.002, 0.01, 0.05, 0.2), "fraction of the record", "logger drops a burst (empty cells)")
def dropout_burst(time, command, position, current, severity, rng):
    out = current.clone()
    out[_burst(out.numel(), severity, rng)] = float("nan")
    return Record(time, command, position, out)


@register("missing_scattered", (0.001, 0.01, 0.05, 0.2), "fraction of the samples", "scattered empty cells")
def missing_scattered(time, command, position, current, severity, rng):
    out = current.clone()
    out[torch.as_tensor(rng.random(out.numel()) < severity)] = float("nan")
    return Record(time, command, position, out)


@register("zero_burst", (0.002, 0.01, 0.05, 0.2), "fraction of the record", "logger writes zeros for a burst")
def zero_burst(time, command, position, current, severity, rng):
    out = current.clone()
    out[_burst(out.numel(), severity, rng)] = 0.0
    return Record(time, command, position, out)


@register("stuck", (0.002, 0.01, 0.05, 0.2), "fraction of the record", "sensor stuck at its last value")
def stuck(time, command, position, current, severity, rng):
    out = current.clone()
    where = _burst(out.numel(), severity, rng)
    out[where] = out[where.start]
    return Record(time, command, position, out)


@register(
    "trigger_offset",
    (0.0005, 0.002, 0.005, 0.01, 0.02),
    "delay [s]",
    "the acquisition starts late: every channel, command included, lags the test command",
)
def trigger_offset(time, command, position, current, severity, rng):
    lag = round(severity * sample_rate(time))
    return Record(time, delayed(command, lag), delayed(position, lag), delayed(current, lag))


@register(
    "current_lag",
    (0.0005, 0.002, 0.005, 0.01, 0.02),
    "delay [s]",
    "the current channel alone lags (another logger, a filter's delay)",
)
def current_lag(time, command, position, current, severity, rng):
    return Record(time, command, position, delayed(current, round(severity * sample_rate(time))))


@register("time_reversal", (1.0,), "-", "every channel written backwards")
def time_reversal(time, command, position, current, severity, rng):
    flip = lambda x: None if x is None else x.flip(0)
    return Record(time, flip(command), flip(position), current.flip(0))


@register("current_reversal", (1.0,), "-", "the current channel alone written backwards")
def current_reversal(time, command, position, current, severity, rng):
    return Record(time, command, position, current.flip(0))


@register("white_noise", (0.05, 0.1, 0.2, 0.4), "noise std / RMS current", "white measurement noise")
def white_noise(time, command, position, current, severity, rng):
    return Record(
        time, command, position, current + severity * _rms(current) * _noise(current.numel(), rng, current.dtype)
    )


@register(
    "coloured_noise",
    (0.05, 0.1, 0.2, 0.4),
    "noise std / RMS current",
    "noise low-passed at 1/100 of the sample rate (pickup, drifting references)",
)
def coloured_noise(time, command, position, current, severity, rng):
    n = current.numel()
    white = _noise(n + 400, rng, torch.float64)
    a = math.exp(-2.0 * math.pi / 100.0)  # one-pole low-pass, corner at f_s / 100
    # the filter's recursion (the 400-tap convolution it replaces agrees to a^400 ~ 1e-11; that convolution kept ~40 MB
    # a call, and 500 records of it took 22 GB)
    filtered = lfilter([1.0], [1.0, -a], white.numpy())[399 : 399 + n]
    coloured = torch.from_numpy(np.ascontiguousarray(filtered))
    coloured = coloured / coloured.std()
    return Record(time, command, position, current + severity * _rms(current) * coloured.to(current.dtype))


@register("hum", (0.05, 0.1, 0.2, 0.4), "hum amplitude / RMS current", f"{HUM_FREQUENCY:g} Hz mains hum")
def hum(time, command, position, current, severity, rng):
    phase = float(rng.uniform(0.0, 2.0 * math.pi))
    tone = torch.sin(2.0 * math.pi * HUM_FREQUENCY * (time - time[0]) + phase).to(current.dtype)
    return Record(time, command, position, current + severity * _rms(current) * tone)


@register("spikes", (0.5, 1.0, 2.0, 5.0), "spike height / RMS current", "20 single-sample spikes (EMI, switching)")
def spikes(time, command, position, current, severity, rng):
    out = current.clone()
    where = torch.as_tensor(rng.choice(out.numel(), 20, replace=False))
    signs = torch.as_tensor(rng.choice([-1.0, 1.0], 20), dtype=out.dtype)
    out[where] += severity * _rms(current) * signs
    return Record(time, command, position, out)


@register("quantisation", (0.005, 0.02, 0.05, 0.1), "LSB / current range", "a coarse ADC")
def quantisation(time, command, position, current, severity, rng):
    finite = current[torch.isfinite(current)]
    lsb = severity * float(finite.max() - finite.min())
    return Record(time, command, position, torch.round(current / lsb) * lsb)


@register("decimate_hold", (2.0, 5.0, 20.0, 50.0), "hold factor (samples)", "a slower logger, each value held")
def decimate_hold(time, command, position, current, severity, rng):
    step = max(1, round(severity))
    index = (torch.arange(current.numel()) // step) * step
    return Record(time, command, position, current[index])


@register("drift", (0.05, 0.1, 0.25, 0.5), "drift over the record / RMS current", "a linear baseline drift")
def drift(time, command, position, current, severity, rng):
    ramp = torch.linspace(0.0, 1.0, current.numel(), dtype=current.dtype)
    return Record(time, command, position, current + severity * _rms(current) * ramp)


def _fast_clock(time: torch.Tensor, x: torch.Tensor | None, severity: float) -> torch.Tensor | None:
    """A channel (n,) as a logger whose clock runs fast by ``severity`` writes it: at t the actuator's at t (1 + s),
    linearly interpolated, its end held past the record."""
    if x is None:
        return None
    t = time - time[0]
    src = (t * (1.0 + severity)).clamp(max=float(t[-1]))
    return torch.as_tensor(np.interp(src.numpy(), t.numpy(), x.double().numpy()), dtype=x.dtype)


@register(
    "clock_error",
    (0.001, 0.005, 0.02, 0.05),
    "relative clock error",
    "the logger's clock runs fast: the current is the actuator's at t (1 + s)",
)
def clock_error(time, command, position, current, severity, rng):
    return Record(time, command, position, _fast_clock(time, current, severity))


@register(
    "logger_clock",
    (0.001, 0.003, 0.005, 0.01),
    "relative clock error",
    "the logger's clock runs fast: every channel is the actuator's at t (1 + s) (its end held)",
)
def logger_clock(time, command, position, current, severity, rng):
    return Record(time, *(_fast_clock(time, x, severity) for x in (command, position, current)))


@register("position_sign", (1.0,), "-", "the position sensor the wrong way round")
def position_sign(time, command, position, current, severity, rng):
    return Record(time, command, None if position is None else -position, current)


@register("position_dead", (1.0,), "-", "the position sensor reads a constant")
def position_dead(time, command, position, current, severity, rng):
    return Record(time, command, None if position is None else torch.zeros_like(position), current)


@register("command_scale", (0.05, 0.1, 0.5, 1.0), "command column x (1 + s)", "the command column in other units")
def command_scale(time, command, position, current, severity, rng):
    return Record(time, None if command is None else command * (1.0 + severity), position, current)
