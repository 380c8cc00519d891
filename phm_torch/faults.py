"""Fault vector k in [0, 1]^8 (paper Table 1) and its mapping to physical parameters.

Every fidelity uses this one mapping (ema_reference.md §2), so HF and LF see the same faults.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import replace
from typing import TYPE_CHECKING

import torch

if TYPE_CHECKING:
    from .plant import Plant

FAULT_NAMES = (
    "dry_friction",
    "backlash",
    "short_a",
    "short_b",
    "short_c",
    "eccentricity",
    "eccentricity_phase",
    "gain_drift",
)
N_FAULTS = len(FAULT_NAMES)


def as_fault_tensor(
    k: torch.Tensor | Sequence[float] | Sequence[Sequence[float]],
    dtype: torch.dtype = torch.float64,
    device: str | torch.device = "cpu",
) -> torch.Tensor:
    """Validate fault vectors and return them as a (B, 8) tensor.

    Args:
        k: one vector (8,) or a batch (B, 8), every entry in [0, 1].

    Raises:
        ValueError: wrong shape, NaN/inf, or an entry outside [0, 1] (named by index and value);
            values are never clamped silently.
    """
    t = torch.as_tensor(k, dtype=dtype, device=device)
    if t.ndim == 1:
        t = t.unsqueeze(0)
    if t.ndim != 2 or t.shape[-1] != N_FAULTS:
        raise ValueError(f"faults must have shape (8,) or (B, 8), got {tuple(t.shape)}")
    if t.shape[0] == 0:
        raise ValueError("faults: empty batch")
    bad = ~torch.isfinite(t)
    if bad.any():
        b, i = (int(v) for v in bad.nonzero()[0])
        raise ValueError(f"faults[{b}][{i}] ({FAULT_NAMES[i]}) is not finite: {t[b, i].item()}")
    out = (t < 0) | (t > 1)
    if out.any():
        b, i = (int(v) for v in out.nonzero()[0])
        raise ValueError(f"faults[{b}][{i}] ({FAULT_NAMES[i]}) = {t[b, i].item():.6g} is outside [0, 1]")
    return t


def apply_faults(plant: Plant, k: torch.Tensor, short_circuit_max: float) -> Plant:
    """A new plant with a validated (B, 8) fault tensor applied (ema_reference.md §2); ``plant`` is unchanged.

    Derives the per-phase tensors ``resistance``, ``inductance``, ``emf`` and ``short`` (B, 3) and the
    eccentricity ``eccentricity`` and ``ecc_phase`` (B,) from the plant's (B,) values, and scales
    ``coulomb_friction``, ``static_friction``, ``backlash`` and ``position_gain`` (B,).
    """
    s = k[:, 2:5].clamp(max=short_circuit_max)  # numerical guard documented in the datasheet
    friction_scale = 1.0 + 2.0 * k[:, 0]
    return replace(
        plant,
        coulomb_friction=plant.coulomb_friction * friction_scale,
        static_friction=plant.static_friction * friction_scale,
        backlash=plant.backlash * (1.0 + 99.0 * k[:, 1]),
        short=s,
        resistance=plant.phase_resistance.unsqueeze(-1) * (1.0 - s),
        inductance=plant.phase_inductance.unsqueeze(-1) * (1.0 - s) ** 2,
        emf=plant.back_emf_constant.unsqueeze(-1) * (1.0 - s),
        eccentricity=0.5 * k[:, 5],
        ecc_phase=-math.pi + 2.0 * math.pi * k[:, 6],
        position_gain=plant.position_gain * (0.5 + k[:, 7]),
    )
