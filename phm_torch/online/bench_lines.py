"""Bench lines: a sinusoid of one fixed frequency, amplitude and phase through a whole current record (mains hum on
a probe or its cable: 400 Hz aircraft power, 50 / 60 Hz ground power), found so that it can be removed before the
pipeline reads the record.

A test command moves the actuator through a record: what its current carries at a frequency comes and goes with the
command (a chirp sweeps its harmonics through), and white noise has no fixed phase. A bench line is the same
complex amplitude in every stretch of the record. :func:`find_lines` cuts the record into ``SEGMENTS`` stretches,
takes each stretch's Hann-windowed spectrum on a fine grid with the phase referred to the record's start, and
calls a frequency a line where ``AGREE_SEGMENTS`` or more stretches agree within ``AGREE`` of the stretches'
componentwise median, a median of ``LINE_MIN`` of the record's RMS current or more. Each line's frequency is then
refined where that median peaks, and its amplitude and phase read there.

The actuator makes such lines too, with large faults only: over the clean val records of three actuators' stores
(1 % noise), lines of 0.5 % of the RMS current or more came from backlash limit cycles (58-101 Hz and a harmonic,
backlash 0.62-0.96, 4 of 400 records) and from two phases shorted at 0.76 or more (lines at a sixth and a quarter of
the sample rate, 3 records); none from any other record. So a line is removed only where the answer without it has
neither (:func:`line_possible`, :func:`~.diagnosis.remove_bench_lines`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from ..faults import FAULT_NAMES
from .rest_offset_check import SHORT_INDEX

SEGMENTS = 8  # stretches of the record a line must agree over
SCREEN_PAD = 4  # zero padding of each stretch's spectrum in the screen (a grid of a quarter stretch bin)
FINE_POINTS = 9  # frequencies tried across one screen bin, where the stretches' phases must agree
MAX_TRIES = 12  # screened peaks looked at, at most
AGREE = 0.25  # a stretch agrees when its complex amplitude is within this fraction of the median's magnitude ...
AGREE_SEGMENTS = 5  # ... and a line needs this many stretches that agree (a chirp's harmonics cross the rest)
LINE_MIN = 0.005  # a line's amplitude over the record's RMS current: smaller ones are left (they move no answer)
LOWEST_BIN = 3  # a line lies at 3 stretch bins (3 x SEGMENTS / T Hz) or above: below, the command's own content
MAX_LINES = 4  # lines removed at most (a hum and its harmonics)
REFINE_PASSES = 3  # Gauss-Newton passes on a line's frequency (_fit)
LINE_BACKLASH = 0.4  # an answer with backlash at or above this may make a limit-cycle line (0.62 the least seen)
LINE_SHORTS = 0.4  # ... as may one with two phases shorted at or above this (0.76 the least seen)
UNEXPLAINED = 0.1  # a fit that leaves this share of its line agreed on by the stretches is not removed
BAND_BINS = 4  # a line is fitted on the record's band within this many stretch bins of it (_band)
EDGE_PERIODS = 2.0  # ... leaving out this many periods of the band's width at either end of the record
MIN_SAMPLES = 64 * SEGMENTS  # a shorter record has no line found in it
BACKLASH_INDEX = FAULT_NAMES.index("backlash")


@dataclass(frozen=True)
class Line:
    """A bench line: ``amplitude`` * cos(2 pi ``frequency`` (t - t_0) + ``phase``), t_0 the record's first time.

    Attributes: frequency [Hz]; amplitude [A]; phase [rad]; share: amplitude over the record's RMS current.
    """

    frequency: float
    amplitude: float
    phase: float
    share: float

    def signal(self, t: torch.Tensor) -> torch.Tensor:
        """The line (n,) at times t (n,) [s], float64."""
        t = t.double() - t.double()[0]
        return self.amplitude * torch.cos(2.0 * math.pi * self.frequency * t + self.phase)

    def text(self) -> str:
        return f"{self.frequency:.5g} Hz at {100.0 * self.share:.3g} % of the RMS current"


def _stretches(x: torch.Tensor) -> tuple[torch.Tensor, int]:
    """The record x (n,) as (SEGMENTS, L) stretches, each less its mean, missing samples at 0, and L."""
    length = x.numel() // SEGMENTS
    seg = x[: SEGMENTS * length].double().reshape(SEGMENTS, length)
    finite = torch.isfinite(seg)
    mean = torch.where(finite, seg, torch.zeros_like(seg)).sum(1, keepdim=True) / finite.sum(1, keepdim=True).clamp(
        min=1
    )
    return torch.where(finite, seg - mean, torch.zeros_like(seg)), length


def _median(z: torch.Tensor, dim: int) -> torch.Tensor:
    """Componentwise median of complex z along ``dim`` (robust to the stretches a command's content dominates)."""
    return torch.complex(z.real.median(dim).values, z.imag.median(dim).values)


def _agreement(z: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """The median (..) over the stretches (dim -2 of z (.., SEGMENTS, m)) and how many stretches agree with it."""
    med = _median(z, -2)
    agree = ((z - med.unsqueeze(-2)).abs() <= AGREE * med.abs().unsqueeze(-2)).sum(-2)
    return med, agree


def _at(seg: torch.Tensor, window: torch.Tensor, rate: float, f: torch.Tensor) -> torch.Tensor:
    """Complex amplitudes (SEGMENTS, m) of the stretches at frequencies f (m,) [Hz], phase referred to the record's
    start (the stretch's window normalised: a line of amplitude a reads a e^{j phase})."""
    length = seg.shape[1]
    t = torch.arange(SEGMENTS * length, dtype=torch.float64).reshape(SEGMENTS, length) / rate
    basis = torch.exp(-2j * math.pi * t.unsqueeze(-1) * f.double())  # (S, L, m)
    return torch.einsum("sl,slm->sm", (seg * window).to(basis.dtype), basis) * (2.0 / float(window.sum()))


def _band(x: torch.Tensor, rate: float, f: float, width: float) -> torch.Tensor:
    """x (n,) with only what lies within ``width`` [Hz] of f [Hz] (a Hann taper over the band): what the command
    puts far below a line (a chirp's current, orders of magnitude larger) would otherwise leak into its fit."""
    n = x.numel()
    freq = torch.fft.rfftfreq(n, 1.0 / rate, dtype=torch.float64)
    taper = torch.where(
        (freq - f).abs() < width, 0.5 * (1.0 + torch.cos(math.pi * (freq - f) / width)), torch.zeros_like(freq)
    )
    return torch.fft.irfft(torch.fft.rfft(x) * taper, n=n)


def _fit(x: torch.Tensor, keep: torch.Tensor, rate: float, f: float) -> tuple[float, complex]:
    """The line near f [Hz] fitted to the record x (n,) by least squares over the samples ``keep`` (n,) bool (the
    stretches that agree on it, finite): its frequency [Hz] and complex amplitude c (the line is Re(c e^{j w t})).

    Gauss-Newton on the frequency: a line at w + d reads a cos wt + b sin wt - d t (a sin wt - b cos wt) to first
    order, so the coefficients c, e of t cos wt and t sin wt give d = (c b - e a) / (a^2 + b^2), ``REFINE_PASSES``
    times (the whole record resolves the frequency, where a stretch's spectrum is a Hann lobe 4 / (L / rate) wide).
    """
    bin_width = SEGMENTS * rate / x.numel()  # a stretch's bin [Hz]
    width = min(BAND_BINS, f / bin_width - 1.0) * bin_width
    x = _band(x, rate, f, width)
    t = torch.arange(x.numel(), dtype=torch.float64) / rate
    # the band's edges ring near the record's ends (a line does not fit the record a whole number of times)
    edge = int(EDGE_PERIODS * rate / width)
    keep = keep & (torch.arange(x.numel()) >= edge) & (torch.arange(x.numel()) < x.numel() - edge)
    centre = float(t[keep].mean())
    t, y = (t - centre)[keep], x[keep]
    for last in [False] * REFINE_PASSES + [True]:
        w = 2.0 * math.pi * f
        cos, sin = torch.cos(w * t), torch.sin(w * t)
        basis = [cos, sin] if last else [cos, sin, t * cos, t * sin]
        coef = torch.linalg.lstsq(torch.stack(basis, 1), y.unsqueeze(1)).solution.flatten().tolist()
        a, b = coef[0], coef[1]
        if not last:
            f += (coef[2] * b - coef[3] * a) / (a * a + b * b) / (2.0 * math.pi)
    # a cos wt + b sin wt about the centre is Re((a - jb) e^{jw(t' - centre)}) in the record's own time t'
    return f, complex(a, -b) * complex(math.cos(-2.0 * math.pi * f * centre), math.sin(-2.0 * math.pi * f * centre))


def _explained(seg: torch.Tensor, window: torch.Tensor, rate: float, line: Line, rms: float) -> bool:
    """Whether the stretches (SEGMENTS, L) less the fitted line agree on less than ``UNEXPLAINED`` of it (or
    ``LINE_MIN`` x ``rms`` [A]) left at its frequency: a fit the command's own content pulled off the line (a 50 Hz hum under a chirp's harmonics)
    would leave a line of its own, and is not removed."""
    length = seg.shape[1]
    t = torch.arange(SEGMENTS * length, dtype=torch.float64).reshape(SEGMENTS, length) / rate
    rest = seg - line.amplitude * torch.cos(2.0 * math.pi * line.frequency * t + line.phase) * (seg != 0)
    med, _ = _agreement(_at(rest, window, rate, torch.tensor([line.frequency], dtype=torch.float64)))
    return float(med.abs()[0]) < max(LINE_MIN * rms, UNEXPLAINED * line.amplitude)


def find_lines(current: torch.Tensor, rate: float) -> list[Line]:
    """The bench lines of a current record (n,) [A] sampled at ``rate`` [Hz] (NaN = missing), strongest first.

    Raises:
        ValueError: a rate that is not a positive number.
    """
    if not (math.isfinite(rate) and rate > 0):
        raise ValueError(f"bench lines: the sample rate must be > 0 Hz, got {rate}")
    x = current.double().flatten()
    finite = torch.isfinite(x)
    if x.numel() < MIN_SAMPLES or int(finite.sum()) < MIN_SAMPLES:
        return []
    rms = float(x[finite].pow(2).mean().sqrt())
    if not rms > 0:
        return []
    seg, length = _stretches(x)
    window = torch.hann_window(length, periodic=False, dtype=torch.float64)
    # screen on magnitudes, which need no common phase reference: a line's stretches each hold nearly all of it
    size = (torch.fft.rfft(seg * window, n=SCREEN_PAD * length, dim=-1) * (2.0 / float(window.sum()))).abs()
    enough = (size >= (1.0 - AGREE) * LINE_MIN * rms).sum(0) >= AGREE_SEGMENTS
    enough[: LOWEST_BIN * SCREEN_PAD] = False
    if not bool(enough.any()):
        return []
    typical = size[:, enough].median(0).values  # and as many stretches of about one size (a command's content varies)
    alike = (size[:, enough] - typical).abs() <= AGREE * typical
    score = torch.zeros(size.shape[1], dtype=torch.float64)
    score[enough] = torch.where(alike.sum(0) >= AGREE_SEGMENTS, typical, torch.zeros_like(typical))
    step = rate / (SCREEN_PAD * length)
    offsets = torch.linspace(-0.5, 0.5, FINE_POINTS, dtype=torch.float64) * step
    lines: list[Line] = []
    for _ in range(MAX_TRIES):
        if len(lines) == MAX_LINES or not bool((score > 0).any()):
            break
        peak = int(score.argmax())
        # the line's main lobe (a Hann window's: two stretch bins either side) is one line, found or not
        score[max(0, peak - 2 * SCREEN_PAD) : peak + 2 * SCREEN_PAD + 1] = 0.0
        grid = peak * step + offsets  # where the stretches' phases, referred to the record's start, agree best
        med, agree = _agreement(_at(seg, window, rate, grid))
        best = int(torch.where(agree >= AGREE_SEGMENTS, med.abs(), torch.zeros_like(med.abs())).argmax())
        if int(agree[best]) < AGREE_SEGMENTS:
            continue
        z = _at(seg, window, rate, grid[best : best + 1])[:, 0]
        near = (z - med[best]).abs() <= AGREE * med[best].abs()
        keep = near.repeat_interleave(length)
        keep = torch.cat([keep, torch.zeros(x.numel() - keep.numel(), dtype=torch.bool)]) & finite
        f, c = _fit(torch.where(finite, x, torch.zeros_like(x)), keep, rate, float(grid[best]))
        line = Line(f, abs(c), math.atan2(c.imag, c.real), abs(c) / rms)
        if line.share >= LINE_MIN and _explained(seg, window, rate, line, rms):
            lines.append(line)
    return lines


def remove_lines(current: torch.Tensor, time: torch.Tensor, lines: list[Line]) -> torch.Tensor:
    """The record (n,) [A] without ``lines`` (its dtype kept; missing samples stay missing)."""
    out = current.double().flatten().clone()
    for line in lines:
        out = out - line.signal(time)
    return out.to(current.dtype).reshape(current.shape)


def line_possible(k_hat: torch.Tensor) -> bool:
    """Whether the answer k_hat (8,) may make a line itself: backlash at ``LINE_BACKLASH`` or more (a limit cycle) or
    two phases shorted at ``LINE_SHORTS`` or more."""
    k = k_hat.double().flatten()
    shorts = k[list(SHORT_INDEX)]
    return bool(k[BACKLASH_INDEX] >= LINE_BACKLASH) or int((shorts >= LINE_SHORTS).sum()) >= 2
