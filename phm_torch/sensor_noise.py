"""Sensor noise on simulated channels: what makes a simulation read like a bench measurement.

White Gaussian noise of an absolute standard deviation per channel (``current`` [A], ``position`` [rad]),
drawn from one seeded generator in a fixed order. Not the noise of the learned surrogates' training and
robustness tests, whose standard deviation is relative to each record's RMS current
(:func:`phm_torch.surrogates.augment.add_noise`).
"""

from __future__ import annotations

from collections.abc import Mapping

import torch

NOISY_CHANNELS = ("current", "position")


def add_sensor_noise(
    channels: Mapping[str, torch.Tensor], std: Mapping[str, float], seed: int
) -> dict[str, torch.Tensor]:
    """Copy of ``channels`` ({name: (..., n)}) with Gaussian noise of std ``std[name]`` (absolute, the channel's
    unit; missing: 0) on ``current`` then ``position``, from ``torch.Generator(seed)``.

    Both draws are always made, in that order, so each channel's noise depends only on the seed and the
    shape, not on the other channel's setting. The other channels are passed through.
    """
    out = dict(channels)
    gen = torch.Generator(device=channels["current"].device).manual_seed(seed)
    for name in NOISY_CHANNELS:
        x = channels[name]
        draw = torch.randn(x.shape, generator=gen, dtype=x.dtype, device=x.device)
        out[name] = x + std.get(name, 0.0) * draw
    return out
