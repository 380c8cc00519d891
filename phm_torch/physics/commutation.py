"""Six-step commutation geometry: trapezoidal back-EMF shape and Hall sectors.

Electrical angle convention (ema_reference.md §1): phase A's trapezoid is flat at +1 for
theta_e in [30°, 150°]; phases B and C lag by 120° and 240°. The Hall sectors are aligned so that in
each 60° sector the driven pair (high, low) sits on its back-EMF flat tops; theta_m(0) = 0.
"""

from __future__ import annotations

import math

import torch

PHASE_OFFSETS = (0.0, 2.0 * math.pi / 3.0, 4.0 * math.pi / 3.0)  # alpha_x for x = a, b, c [rad]

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
    ramp_down = 1.0 - (x - 5 * math.pi / 6) / (math.pi / 6)                           # +1 at 150°, -1 at 210°
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


def sector_masks(sector: torch.Tensor, dtype: torch.dtype) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """One-hot (B, 3) masks of the high, low and off phase for each sample's sector."""
    table = torch.tensor(SECTOR_TABLE, device=sector.device)[sector]  # (B, 3)
    eye = torch.eye(3, dtype=dtype, device=sector.device)
    return eye[table[:, 0]], eye[table[:, 1]], eye[table[:, 2]]


def emf_constants(theta_m: torch.Tensor, plant) -> torch.Tensor:
    """Per-phase EMF constants with eccentricity modulation, (B,) -> (B, 3) [V s/rad].

    k_e,x(theta_m) = k_e,x * (1 + eps * cos(theta_m - phi - alpha_x)) (ema_reference.md §2).
    """
    arg = (theta_m - plant.ecc_phase).unsqueeze(-1) - theta_m.new_tensor(PHASE_OFFSETS)
    return plant.emf * (1.0 + plant.eccentricity.unsqueeze(-1) * torch.cos(arg))
