"""Six-step commutation geometry: trapezoidal back-EMF shape and Hall sectors.

Electrical angle convention (ema_reference.md §1): phase A's trapezoid is flat at +1 for
theta_e in [30°, 150°]; phases B and C lag by 120° and 240°. The Hall sectors are aligned so that in
each 60° sector the driven pair (high, low) sits on its back-EMF flat tops; theta_m(0) = 0.
"""

from __future__ import annotations

import math

import torch

PHASE_OFFSETS = (0.0, 2.0 * math.pi / 3.0, 4.0 * math.pi / 3.0)  # alpha_x for x = a, b, c [rad]
_COS = tuple(math.cos(a) for a in PHASE_OFFSETS)
_SIN = tuple(math.sin(a) for a in PHASE_OFFSETS)

# Sector s covers theta_e in [30° + 60° s, 90° + 60° s); columns: (high, low, off) phase indices.
SECTOR_TABLE = ((0, 1, 2), (0, 2, 1), (1, 2, 0), (1, 0, 2), (2, 0, 1), (2, 1, 0))


def trapezoid(angle: torch.Tensor) -> torch.Tensor:
    """Unit trapezoidal back-EMF shape of one phase, flat +1 on [30°, 150°], -1 on [210°, 330°].

    Args:
        angle: electrical angle of the phase, any shape [rad].
    Returns:
        Tensor of the same shape in [-1, 1].
    """
    x = torch.remainder(angle, 2.0 * math.pi)
    rise = (x < math.pi / 6) | (x >= 11 * math.pi / 6)
    ramp_up = torch.remainder(x + math.pi / 6, 2.0 * math.pi) / (math.pi / 6) - 1.0  # -1 at 330°, +1 at 30°
    ramp_down = 1.0 - (x - 5 * math.pi / 6) / (math.pi / 6)  # +1 at 150°, -1 at 210°
    flat = torch.where(x < math.pi, torch.ones_like(x), -torch.ones_like(x))
    out = torch.where((x >= 5 * math.pi / 6) & (x < 7 * math.pi / 6), ramp_down, flat)
    return torch.where(rise, ramp_up, out)


def phase_shapes(theta_e: torch.Tensor) -> torch.Tensor:
    """Trapezoids of the three phases: (B,) electrical angle -> (B, 3)."""
    angles = theta_e.unsqueeze(-1) - theta_e.new_tensor(PHASE_OFFSETS)
    return trapezoid(angles)


def hall_sector(theta_e: torch.Tensor) -> torch.Tensor:
    """Hall sector index 0..5 of a (B,) electrical angle (int64)."""
    return torch.floor(torch.remainder(theta_e - math.pi / 6, 2.0 * math.pi) / (math.pi / 3)).long().clamp(0, 5)


def eccentricity_factors(theta_m: torch.Tensor, eccentricity: torch.Tensor, phase: torch.Tensor) -> list[torch.Tensor]:
    """EMF-constant modulation of an eccentric rotor, 1 + eps cos(theta_m - phi - alpha_x), for x = a, b, c.

    An eccentric rotor modulates each phase's EMF constant once per mechanical revolution:
    k_e,x(theta_m) = k_e,x (1 + eps cos(theta_m - phi - alpha_x)) (ema_reference.md §2). Both motors use
    it (HF per phase, LF inside k_eq).

    Args:
        theta_m: motor angle (B,) [rad].  eccentricity: eps (B,) [-].  phase: phi (B,) [rad].
    Returns:
        Three (B,) tensors (phases kept apart: reductions over a trailing 3 are slow on CPU).
    """
    arg = theta_m - phase
    c, s = torch.cos(arg), torch.sin(arg)
    return [1.0 + eccentricity * (c * _COS[x] + s * _SIN[x]) for x in range(3)]
