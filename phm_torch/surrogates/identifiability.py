"""How smoothly a measured signal depends on the fault vector: a bound that no FDI network beats.

The FDI network is a smooth map from a few POD coefficients to k. It can only be as accurate as the
signal is a smooth function of k. Where a change of 1e-3 in k already moves the signal as much as a
change of 1e-2 (stick-slip, current saturation, a limit cycle whose phase depends on every parameter),
the signal carries no usable information about k below ~1e-2, whatever the network, the data volume
or the number of modes.

:func:`signal_sensitivity` measures this locally. For each fault vector it simulates the signal after
steps of several sizes in a random direction, and reports the RMS signal change per step. A smooth
response changes in proportion to the step: the ratio of the changes at two step sizes equals the ratio
of the steps. A rough response changes nearly as much at the smallest step as at the largest.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import torch

from .metrics import ECC_PHASE


def signal_sensitivity(
    simulate: Callable[[torch.Tensor], torch.Tensor],
    k: torch.Tensor,
    steps: Sequence[float] = (1e-3, 1e-2, 1e-1),
    frozen: Sequence[int] = (ECC_PHASE,),
    seed: int = 0,
) -> dict[str, torch.Tensor]:
    """RMS change of the signal after steps of each size in k.

    Each fault vector gets one random unit direction (the ``frozen`` columns, by default the
    eccentricity phase, which is not a damage, are left alone). A component that would leave [0, 1]
    steps the other way, so every step has its nominal length.

    Args:
        simulate: fault vectors (B, 8) float64 -> signals (B, n_e), e.g. the envelope current [A].
        k: (n, 8) fault vectors in [0, 1].
        steps: step lengths (Euclidean, in units of k), increasing.
        frozen: columns of k never moved.
        seed: seed of the directions.

    Returns:
        ``rms_change`` (n, len(steps)) [signal unit], ``signal_rms`` (n,) [signal unit], ``steps``
        (len(steps),), and ``linearity`` (n,): the change at the smallest step divided by the change at the
        largest, times the ratio of the steps; 1 for a signal linear in k, large where it is rough.
    """
    k = torch.as_tensor(k, dtype=torch.float64)
    if k.ndim != 2 or k.shape[1] != 8:
        raise ValueError(f"k must be (n, 8), got {tuple(k.shape)}")
    if len(steps) < 2 or any(not 0 < s < 1 for s in steps) or list(steps) != sorted(steps):
        raise ValueError(f"steps must be at least two increasing lengths in (0, 1), got {list(steps)}")
    if any(not 0 <= c < 8 for c in frozen):
        raise ValueError(f"frozen must be columns 0..7, got {list(frozen)}")
    gen = torch.Generator().manual_seed(seed)
    direction = torch.randn(k.shape, generator=gen, dtype=torch.float64)
    direction[:, list(frozen)] = 0.0
    direction = direction / direction.norm(dim=1, keepdim=True)
    moved = []
    for s in steps:
        d = s * direction
        d = torch.where((k + d > 1.0) | (k + d < 0.0), -d, d)
        moved.append(k + d)
    with torch.no_grad():
        signals = simulate(torch.cat([k, *moved]))
    n = k.shape[0]
    base, rest = signals[:n], signals[n:].reshape(len(steps), n, -1)
    change = (rest - base).pow(2).mean(-1).sqrt().T  # (n, len(steps))
    tiny = torch.finfo(torch.float64).tiny
    linearity = change[:, 0] / change[:, -1].clamp(min=tiny) * (steps[-1] / steps[0])
    return {
        "rms_change": change,
        "signal_rms": base.pow(2).mean(-1).sqrt(),
        "steps": torch.tensor(list(steps), dtype=torch.float64),
        "linearity": linearity,
    }
