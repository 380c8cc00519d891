"""Stability margins and bandwidth from a sampled frequency response, batched.

Between two test frequencies the gain [dB] and the unwrapped phase [deg] are interpolated linearly
in log-frequency. Conventions (``nan`` = not measurable on the test grid, which fails any requirement):

* crossover: the first frequency where |L| falls through 1; ``nan`` if |L| stays on one side of 1.
* phase margin: 180 deg + phase of L at the crossover [deg], phase unwrapped from the lowest frequency.
* phase crossover: the first frequency where the phase of L falls through -180 deg; gain margin
  = -20 log10 |L| there [dB]; ``nan`` if the phase stays above -180 deg on the grid.
* bandwidth: the first frequency where |T| falls below 1/sqrt(2) (-3 dB from the unit DC gain of this
  type-1 loop); ``inf`` if |T| stays above it on the whole grid, ``nan`` if it is already below at
  the lowest frequency.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch

# |L| [dB] below which a sweep reading is no response (SineSweep.no_response_db's default): 1 % of the command, where a
# loop whose output sticks in dry friction reads -47 to -320 dB and a responding one, past its phase crossover, -9 to -20
NO_RESPONSE_DB = -40.0
MARGIN_NAMES = ("crossover_hz", "phase_margin_deg", "phase_crossover_hz", "gain_margin_db", "bandwidth_hz")


@dataclass
class Margins:
    """Per fault vector, every field (B,) float64 (see the module docstring for nan/inf)."""

    crossover_hz: torch.Tensor
    phase_margin_deg: torch.Tensor
    phase_crossover_hz: torch.Tensor
    gain_margin_db: torch.Tensor
    bandwidth_hz: torch.Tensor

    def as_dict(self) -> dict[str, torch.Tensor]:
        return {name: getattr(self, name) for name in MARGIN_NAMES}

    def stacked(self) -> torch.Tensor:
        """(B, 5) in the order of ``MARGIN_NAMES``."""
        return torch.stack([getattr(self, n) for n in MARGIN_NAMES], -1)

    @classmethod
    def from_stacked(cls, stacked: torch.Tensor) -> Margins:
        """The inverse of :meth:`stacked`: (B, 5) in the order of ``MARGIN_NAMES``."""
        return cls(*stacked.unbind(-1))

    def take_rows(self, rows: torch.Tensor | slice) -> Margins:
        """The margins of ``rows`` (an index tensor or a slice)."""
        return Margins.from_stacked(self.stacked()[rows])

    def put_rows(self, rows: torch.Tensor, other: Margins) -> Margins:
        """A copy with ``rows`` replaced by ``other`` (one row of other per index)."""
        out = self.stacked().clone()
        out[rows] = other.stacked()
        return Margins.from_stacked(out)


# The requirements that a margin column decides, and its column: a nan there is "not measurable on the grid".
UNMEASURABLE_COLUMNS = {"phase_margin": 1, "gain_margin": 3, "bandwidth": 4}


def unmeasurable_counts(stacked: np.ndarray | torch.Tensor) -> dict[str, int]:
    """How many rows of a (n, 5) ``Margins.stacked()`` array have a phase margin, gain margin or bandwidth
    that could not be measured on the grid (nan; such a row is labelled faulty). An ``inf`` bandwidth
    (|T| above -3 dB on the whole grid) is a measured lower bound, not counted."""
    a = np.asarray(stacked, dtype=np.float64).reshape(-1, len(MARGIN_NAMES))
    return {name: int(np.isnan(a[:, col]).sum()) for name, col in UNMEASURABLE_COLUMNS.items()}


def first_fall(x: torch.Tensor, level: float) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """First falling crossing of ``level`` by the rows of x (B, F).

    Returns:
        index i (B,) of the grid point before the crossing, fraction s (B,) in [0, 1] of the way to
        i + 1 (linear in x), and ``found`` (B,) bool. Rows never crossing get i = 0, s = 0, found False.
    """
    above = x >= level
    falls = above[:, :-1] & ~above[:, 1:]
    found = falls.any(-1)
    i = torch.where(found, falls.to(torch.int64).argmax(-1), torch.zeros_like(found, dtype=torch.int64))
    x0 = x.gather(-1, i[:, None])[:, 0]
    x1 = x.gather(-1, (i + 1).clamp(max=x.shape[-1] - 1)[:, None])[:, 0]
    s = torch.where(found, (x0 - level) / (x0 - x1).clamp(min=1e-300), torch.zeros_like(x0))
    return i, s.clamp(0.0, 1.0), found


def _at(values: torch.Tensor, i: torch.Tensor, s: torch.Tensor) -> torch.Tensor:
    """values (B, F) or (F,) linearly interpolated at fractional index i + s (B,)."""
    if values.ndim == 1:
        values = values.expand(i.shape[0], -1)
    v0 = values.gather(-1, i[:, None])[:, 0]
    v1 = values.gather(-1, (i + 1).clamp(max=values.shape[-1] - 1)[:, None])[:, 0]
    return v0 + s * (v1 - v0)


def unwrapped_phase_deg(h: torch.Tensor) -> torch.Tensor:
    """Phase of h (B, F) complex in degrees, unwrapped along the frequency axis, starting in (-180, 180]."""
    ph = torch.angle(h)
    d = torch.diff(ph, dim=-1)
    d = d - 2.0 * math.pi * torch.round(d / (2.0 * math.pi))
    return torch.rad2deg(torch.cat([ph[:, :1], ph[:, :1] + torch.cumsum(d, -1)], -1))


def margins(
    frequencies: torch.Tensor,
    open_loop: torch.Tensor,
    closed_loop: torch.Tensor,
    no_response_db: float | None = None,
) -> Margins:
    """Margins of a batch of measured loops.

    Args:
        frequencies: (F,) test frequencies [Hz], increasing, or (B, F) non-decreasing per vector (refined).
        open_loop: (B, F) complex L(jw).  closed_loop: (B, F) complex T(jw).
        no_response_db: |L| [dB] below which a reading is no response (the output stuck in dry friction: its phase
            is noise). The phase crossover is then sought only up to the first such reading, and where the phase has
            not fallen through -180 deg there, the gain margin is the lower bound -|L| [dB] at the last responding
            frequency (the phase crossover stays nan). None: every reading counts.
    """
    logf = torch.log(frequencies.to(torch.float64))
    nan = torch.full(open_loop.shape[:1], math.nan, dtype=torch.float64, device=open_loop.device)
    gain_db = 20.0 * torch.log10(open_loop.abs().clamp(min=1e-300))
    phase = unwrapped_phase_deg(open_loop)

    i, s, ok = first_fall(gain_db, 0.0)
    crossover = torch.where(ok, torch.exp(_at(logf, i, s)), nan)
    pm = torch.where(ok, 180.0 + _at(phase, i, s), nan)

    responding = torch.ones_like(gain_db, dtype=torch.bool)
    if no_response_db is not None:  # the readings up to the first one that does not respond
        responding = (gain_db > no_response_db).to(torch.int64).cumprod(-1).bool()
    i, s, ok = first_fall(torch.where(responding, phase, math.inf), -180.0)
    phase_crossover = torch.where(ok, torch.exp(_at(logf, i, s)), nan)
    gm = torch.where(ok, -_at(gain_db, i, s), nan)
    last = responding.sum(-1) - 1  # the last responding reading; a tail that does not respond bounds the margin
    bounded = ~ok & (last >= 0) & (last < gain_db.shape[-1] - 1)
    gm = torch.where(bounded, -gain_db.gather(-1, last.clamp(min=0)[:, None])[:, 0], gm)

    t_db = 20.0 * torch.log10(closed_loop.abs().clamp(min=1e-300))
    level = -10.0 * math.log10(2.0)
    i, s, ok = first_fall(t_db, level)
    bw = torch.where(ok, torch.exp(_at(logf, i, s)), nan)
    bw = torch.where(~ok & (t_db[:, 0] >= level), torch.full_like(bw, math.inf), bw)
    return Margins(crossover, pm, phase_crossover, gm, bw)
