"""Measurement corruption for end-to-end training and robustness tests: noise and missing samples."""

from __future__ import annotations

import torch
from torch import nn


def rms(signals: torch.Tensor) -> torch.Tensor:
    """(B,) RMS of full records (B, n_e) [A]: the scale that relative current noise refers to."""
    return signals.pow(2).mean(-1).sqrt()


def add_noise(samples: torch.Tensor, scale: torch.Tensor, relative_std: float | torch.Tensor,
              generator: torch.Generator | None = None) -> torch.Tensor:
    """samples (B, n_w) + Gaussian noise of std ``relative_std * scale``; scale (B,) [A] (e.g. the RMS current),
    relative_std a float or (B,)."""
    std = torch.as_tensor(relative_std, dtype=samples.dtype, device=samples.device) * scale   # (B,)
    noise = torch.randn(samples.shape, generator=generator, dtype=samples.dtype, device=samples.device)
    return samples + noise * std.unsqueeze(-1)


def drop_samples(samples: torch.Tensor, n_missing: int | torch.Tensor,
                 generator: torch.Generator | None = None) -> torch.Tensor:
    """Copy of samples (B, n_w) with ``n_missing`` (int or (B,) ints) random samples per row set to NaN."""
    b, n = samples.shape
    count = torch.as_tensor(n_missing, device=samples.device).expand(b)
    if b and int(count.max()) > n:
        raise ValueError(f"cannot drop {int(count.max())} of {n} samples")
    rank = torch.rand((b, n), generator=generator, device=samples.device).argsort(-1).argsort(-1)
    return samples.masked_fill(rank < count.unsqueeze(-1), float("nan"))


class SignalAugment(nn.Module):
    """Random corruption of training samples: each signal gets noise of relative std drawn uniformly in
    [0, ``noise``] (times its RMS current) and a number of missing samples drawn uniformly in
    {0, ..., ``max_missing``}.

    Args:
        noise: largest relative noise std (0.01 = 1 % of the signal's RMS current).
        max_missing: largest number of missing samples per signal.
    """

    def __init__(self, noise: float = 0.01, max_missing: int = 3):
        super().__init__()
        if not noise >= 0:
            raise ValueError(f"model.augment.noise must be >= 0, got {noise!r}")
        if isinstance(max_missing, bool) or not isinstance(max_missing, int) or max_missing < 0:
            raise ValueError(f"model.augment.max_missing must be an integer >= 0, got {max_missing!r}")
        self.noise, self.max_missing = float(noise), max_missing

    def forward(self, samples: torch.Tensor, scale: torch.Tensor) -> torch.Tensor:
        b = samples.shape[0]
        rel = torch.rand(b, dtype=samples.dtype, device=samples.device) * self.noise
        out = add_noise(samples, scale, rel)
        if self.max_missing:
            out = drop_samples(out, torch.randint(0, self.max_missing + 1, (b,), device=samples.device))
        return out
