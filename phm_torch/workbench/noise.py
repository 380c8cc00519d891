"""Noise-floor estimate: the white part of a signal, read from its spectrum above the physics.

Every modelled channel is band-limited (the current by the 1 kHz filter, the position by the mechanics
and the LVDT lag), so the power spectral density of the residual (measurement - model) in the top band
of the spectrum, here [0.25, 0.5] f_s by default, is the measurement noise. For white noise of standard
deviation sigma the one-sided density is 2 sigma^2 / f_s, hence sigma^2 = mean(PSD over the band) f_s / 2.
Using the residual rather than the raw measurement removes whatever fast content the model does explain.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.signal import welch

from .. import checks


@dataclass(frozen=True)
class HighBandNoise:
    """Estimator of the white-noise standard deviation of a sampled signal.

    Attributes:
        band: (low, high) edges of the band as fractions of the sample rate, 0 <= low < high <= 0.5.
        segment: Welch segment length [samples].
    """

    band: tuple[float, float] = (0.25, 0.5)
    segment: int = 256

    def __post_init__(self) -> None:
        band = checks.numbers(self.band, "noise.band")
        if len(band) != 2 or not 0.0 <= band[0] < band[1] <= 0.5:
            raise ValueError(
                f"noise.band must be [low, high] with 0 <= low < high <= 0.5 (fractions of f_s), got {list(band)}"
            )
        object.__setattr__(self, "band", band)
        object.__setattr__(self, "segment", checks.integer(self.segment, "noise.segment", 16))

    def __call__(self, x: np.ndarray, sample_rate: float) -> float:
        """Standard deviation [unit of x] of the white noise in ``x`` (n,), sampled at ``sample_rate`` [Hz]."""
        x = np.asarray(x, dtype=np.float64)
        if x.ndim != 1 or x.size < 16:
            raise ValueError(f"noise estimate needs a 1-D signal of >= 16 samples, got shape {x.shape}")
        f, psd = welch(x, fs=sample_rate, nperseg=min(self.segment, x.size), detrend="constant")
        lo, hi = self.band[0] * sample_rate, self.band[1] * sample_rate
        sel = (f >= lo) & (f < hi) & (f > 0)
        if not sel.any():
            raise ValueError(f"noise.band {self.band} holds no spectral bin at segment {self.segment}")
        return float(np.sqrt(np.mean(psd[sel]) * sample_rate / 2.0))
