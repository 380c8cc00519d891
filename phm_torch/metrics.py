"""Signal metrics used across phm_torch (tracking, NRMSE, sinusoid fits). Fractions, not percent."""

from __future__ import annotations

import math

import numpy as np
import torch


def finite_mean(x: torch.Tensor) -> torch.Tensor:
    """Mean over the last dimension of the finite values of x (..., n) (NaN and inf left out; 0 if none)."""
    finite = torch.isfinite(x)
    return torch.where(finite, x, torch.zeros_like(x)).sum(-1) / finite.sum(-1).clamp(min=1)


def nrmse(signal: torch.Tensor, reference: torch.Tensor) -> torch.Tensor:
    """RMS of (signal - reference) over the last axis, divided by the reference's range (max - min); (...,)
    fraction.

    A constant reference (range 0) gives no scale to divide by, so its NRMSE is undefined and is NaN,
    whatever the signal: not RMS / tiny (an absurd figure) nor 0 / tiny (a perfect match that means
    nothing). Reports write it as null.
    """
    rng = reference.amax(-1) - reference.amin(-1)
    rms = (signal - reference).pow(2).mean(-1).sqrt()
    return torch.where(rng > 0, rms / rng, torch.nan)


def sine_fit(time: np.ndarray, signal: np.ndarray, phase: np.ndarray) -> tuple[float, float]:
    """Least-squares fit signal ~ a sin(phase) + b cos(phase) + c; returns (amplitude, phase offset [rad])."""
    basis = np.stack([np.sin(phase), np.cos(phase), np.ones_like(phase)], axis=1)
    a, b, _ = np.linalg.lstsq(basis, signal, rcond=None)[0]
    return math.hypot(a, b), math.atan2(b, a)


def chirp_last_cycle(
    time: torch.Tensor, command: torch.Tensor, position: torch.Tensor, f_end: float, duration: float
) -> tuple[float, float]:
    """Amplitude ratio and lag [deg] of position vs a linear 0 -> f_end chirp over its last cycle."""
    t = time.detach().cpu().numpy()
    mask = t >= duration - 1.0 / f_end
    phase = 2 * math.pi * 0.5 * (f_end / duration) * t[mask] ** 2
    ac, pc = sine_fit(t[mask], command.detach().cpu().numpy()[mask], phase)
    ap, pp = sine_fit(t[mask], position.detach().cpu().numpy()[mask], phase)
    return ap / ac, math.degrees(pc - pp)
