"""Measurement corruption for end-to-end training and robustness tests: noise and missing samples."""

from __future__ import annotations

import math

import torch
from torch import nn


def rms(signals: torch.Tensor) -> torch.Tensor:
    """(B,) RMS of full records (B, n_e) [A]: the scale that relative current noise refers to."""
    # a norm, not pow(2).mean(): no record-sized temporary (3.2 GB for an 80,000-record store)
    return torch.linalg.vector_norm(signals, dim=-1) / signals.shape[-1] ** 0.5


def clipped_mean_factor(clip: float = 3.0, passes: int = 2) -> float:
    """What :func:`noise_level`'s robust mean of |d| gives for white noise of unit std: the mean of |g|,
    then ``passes`` times the mean of min(|g|, clip x the previous value), g ~ N(0, 6) (the second
    difference of unit white noise; E min(|g|, a) = sqrt(2/pi) (1 - exp(-a^2/2)) + a erfc(a / sqrt(2)) for
    g ~ N(0, 1))."""
    m = math.sqrt(2.0 / math.pi)
    for _ in range(passes):
        a = clip * m
        m = math.sqrt(2.0 / math.pi) * (1.0 - math.exp(-a * a / 2.0)) + a * math.erfc(a / math.sqrt(2.0))
    return m * math.sqrt(6.0)


def noise_level(x: torch.Tensor, window: int = 0) -> torch.Tensor:
    """Relative white-noise level (B,) of full records x (B, n_e) [A]: std of the noise over the record's
    RMS, from the second differences d = x[i+1] - 2 x[i] + x[i-1].

    A robust mean of |d|: the mean, then twice the mean of |d| clipped at 3 x the previous value, divided
    by what that gives for Gaussian white noise (``clipped_mean_factor()``, so it is unbiased for it). The
    1 kHz-filtered current sampled at 20 kHz barely feeds d, and the clipping keeps the short ringing after
    Hall edges out: on 300 noise-free val records of the paper store it reads 0.02 % (median; 0.07 % at
    the 90th percentile), and with 0.5 / 1 / 3 / 10 % white noise added 0.53 / 1.02 / 3.01 / 9.96 %
    (median), as a median of |d| does, without its sort. Missing (NaN) samples are left out.

    ``window`` > 0: d over the first ``window`` samples only and the RMS over every (4 n_e // window)-th
    sample, for a stationary noise the same level to ~5 % (1024 samples) at a tenth of the cost (the online step).
    """
    n = x.shape[1]
    w = x if window <= 0 else x[:, : window + 2]
    xs = x if window <= 0 else x[:, :: noise_spacing(n, window)]  # a quarter as many: cache lines skipped
    return noise_from_parts(w, xs)


def noise_spacing(n: int, window: int) -> int:
    """Spacing of the samples :func:`noise_level` (``window`` > 0) takes the RMS of, for records of n samples."""
    return max(1, 4 * n // window)


def noise_from_parts(w: torch.Tensor, xs: torch.Tensor) -> torch.Tensor:
    """:func:`noise_level` from its two reads of the records: the consecutive samples ``w`` (B, m) the second
    differences come from and the samples ``xs`` (B, p) the RMS comes from (a caller that gathers them itself,
    e.g. with the other columns a step reads, passes them here)."""
    d2 = (w[:, 2:] - 2.0 * w[:, 1:-1] + w[:, :-2]).abs()
    present = torch.isfinite(d2)
    d2 = torch.where(present, d2, torch.zeros_like(d2))
    count = present.sum(1).clamp(min=1)
    m = d2.sum(1) / count
    for _ in range(2):  # literals: TorchScript reads no Python globals
        m = torch.minimum(d2, 3.0 * m.unsqueeze(1)).sum(1) / count
    finite = torch.isfinite(xs)
    level = torch.where(finite, xs, torch.zeros_like(xs)).pow(2).sum(1) / finite.sum(1).clamp(min=1)
    return m / 1.9401301101495292 / level.sqrt().clamp(min=1e-12)


def add_noise(
    samples: torch.Tensor,
    scale: torch.Tensor,
    relative_std: float | torch.Tensor,
    generator: torch.Generator | None = None,
) -> torch.Tensor:
    """samples (B, n_w) + Gaussian noise of std ``relative_std * scale``; scale (B,) [A] (e.g. the RMS current),
    relative_std a float or (B,). (Absolute sensor noise on simulated channels: :mod:`phm_torch.sensor_noise`.)"""
    std = torch.as_tensor(relative_std, dtype=samples.dtype, device=samples.device) * scale  # (B,)
    noise = torch.randn(samples.shape, generator=generator, dtype=samples.dtype, device=samples.device)
    return samples + noise * std.unsqueeze(-1)


def drop_samples(
    samples: torch.Tensor, n_missing: int | torch.Tensor, generator: torch.Generator | None = None
) -> torch.Tensor:
    """Copy of samples (B, n_w) with ``n_missing`` (int or (B,) ints) random samples per row set to NaN."""
    b, n = samples.shape
    count = torch.as_tensor(n_missing, device=samples.device).expand(b)
    if b and int(count.max()) > n:
        raise ValueError(f"cannot drop {int(count.max())} of {n} samples")
    rank = torch.rand((b, n), generator=generator, device=samples.device).argsort(-1).argsort(-1)
    return samples.masked_fill(rank < count.unsqueeze(-1), float("nan"))


def shifted_samples(records: torch.Tensor, indices: torch.Tensor, shift: torch.Tensor) -> torch.Tensor:
    """The samples (B, n_w) at ``indices`` (n_w,) of records (B, n_e), each record read moved by its own ``shift``
    (B, 1) [samples]: ``x[i + shift]``, the end values held (a trigger that is not exact, as a training record)."""
    n = records.shape[1]
    return torch.gather(records, 1, (indices.unsqueeze(0) + shift).clamp(0, n - 1))


class SignalAugment(nn.Module):
    """Random corruption of training samples: each signal gets noise of relative std drawn uniformly in
    [0, ``noise``] (times its RMS current) and a number of missing samples drawn uniformly in
    {0, ..., ``max_missing``}; with ``max_shift``, its samples are first taken from the full record moved by a
    number of samples drawn uniformly in {-max_shift, ..., max_shift} (a trigger that is not exact).

    Args:
        noise: largest relative noise std (0.01 = 1 % of the signal's RMS current).
        max_missing: largest number of missing samples per signal.
        max_shift: largest shift [samples of the store's grid] (20 at 20 kHz: 1 ms); 0: records on time.
    """

    def __init__(self, noise: float = 0.01, max_missing: int = 3, max_shift: int = 0):
        super().__init__()
        if not noise >= 0:
            raise ValueError(f"model.augment.noise must be >= 0, got {noise!r}")
        for name, value in (("max_missing", max_missing), ("max_shift", max_shift)):
            if isinstance(value, bool) or not isinstance(value, int) or value < 0:
                raise ValueError(f"model.augment.{name} must be an integer >= 0, got {value!r}")
        self.noise, self.max_missing, self.max_shift = float(noise), max_missing, max_shift

    def select(self, records: torch.Tensor, indices: torch.Tensor) -> torch.Tensor:
        """The samples (B, n_w) at ``indices`` (n_w,) of full records (B, n_e), each record read moved by its own
        random shift within +- ``max_shift`` (:func:`shifted_samples`)."""
        shift = torch.randint(-self.max_shift, self.max_shift + 1, (records.shape[0], 1), device=records.device)
        return shifted_samples(records, indices, shift)

    def corrupt(self, samples: torch.Tensor, scale: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Corrupted copy of samples (B, n_w) [A], and the relative noise std (B,) each row got (what a
        noise-aware network is told); scale (B,) [A] the signals' RMS current."""
        b = samples.shape[0]
        rel = torch.rand(b, dtype=samples.dtype, device=samples.device) * self.noise
        out = add_noise(samples, scale, rel)
        if self.max_missing:
            out = drop_samples(out, torch.randint(0, self.max_missing + 1, (b,), device=samples.device))
        return out, rel

    def forward(self, samples: torch.Tensor, scale: torch.Tensor) -> torch.Tensor:
        return self.corrupt(samples, scale)[0]
