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

    State (B, 2) = [y, dy/dt]; ``step`` takes the input averaged over the step [A] (B,).
    """

    def __init__(self, cutoff_hz: float, h: float, dtype: torch.dtype, device: torch.device):
        wc = 2.0 * math.pi * cutoff_hz
        a = np.array([[0.0, 1.0], [-wc * wc, -math.sqrt(2.0) * wc]])
        b = np.array([[0.0], [wc * wc]])
        m = np.zeros((3, 3))
        m[:2, :2], m[:2, 2:] = a * h, b * h
        e = scipy.linalg.expm(m)
        self.ad = torch.tensor(e[:2, :2].T, dtype=dtype, device=device)  # transposed for row vectors
        self.bd = torch.tensor(e[:2, 2], dtype=dtype, device=device)

    def step(self, state: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
        return state @ self.ad + u.unsqueeze(-1) * self.bd
