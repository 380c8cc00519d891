"""Sensors and signal conditioning shared by every fidelity: LVDT lag and the current filter."""

from __future__ import annotations

import math

import numpy as np
import scipy.linalg
import torch


def lvdt_step(reading: torch.Tensor, position: torch.Tensor, tau: torch.Tensor, h: float) -> torch.Tensor:
    """First-order LVDT lag advanced exactly over h for a held input.

    Args:
        reading: previous LVDT output [rad] (B,).  position: true user angle [rad] (B,).
        tau: time constant [s] (B,), zero meaning an ideal sensor.
    """
    decay = torch.exp(-h / tau.clamp(min=1e-12))
    return position + (reading - position) * decay


class ButterworthFilter:
    """Continuous 2nd-order Butterworth low-pass, discretised exactly (zero-order hold) at step h.

    State = (y, dy/dt), each (B,); ``step`` takes the input averaged over the step [A] (B,).
    """

    def __init__(self, cutoff_hz: float, h: float, dtype: torch.dtype, device: torch.device):
        wc = 2.0 * math.pi * cutoff_hz
        a = np.array([[0.0, 1.0], [-wc * wc, -math.sqrt(2.0) * wc]])
        b = np.array([[0.0], [wc * wc]])
        m = np.zeros((3, 3))
        m[:2, :2], m[:2, 2:] = a * h, b * h
        e = scipy.linalg.expm(m)
        # Python floats: elementwise updates fuse, a (B, 2) @ (2, 2) product would not.
        self.ad = [[float(v) for v in row] for row in e[:2, :2]]
        self.bd = [float(v) for v in e[:2, 2]]

    def step(self, state: tuple[torch.Tensor, torch.Tensor], u: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Advance (y [A], dy/dt [A/s]), each (B,), by one step with input u (B,) [A]."""
        y, dy = state
        (a00, a01), (a10, a11) = self.ad
        return a00 * y + a01 * dy + self.bd[0] * u, a10 * y + a11 * dy + self.bd[1] * u
