"""RUL of posterior particles: each particle (k, s) propagated noise-free until the pipeline's health classifier
f turns faulty, then 5/50/95 % over the particles.

The noise-free solution with rate scale s is k(t; sF) = k(st; F): one search on the wear clock tau = s t gives
tau*(k), and the particle's RUL is tau* / s. The search runs on a geometric coarse grid of the wear clock
(0, dt, 2 dt, 4 dt, ...; dt the pipeline's grid step), then bisects the first faulty interval
``bisections`` times and interpolates the score's zero linearly; off-grid points are expm(F j dt) expm(F d) dk
with the short step d by Taylor series (:meth:`DamageLaw.propagate`). The relative accuracy is about
2^-bisections of the coarse ratio before the interpolation, far below the band's own spread.

Future eps (the rate disturbance after the last inspection) widens the band beyond the (k, s) posterior: each
particle's wear clock is sped up by a factor r, lognormal with a two-piece log-std fitted to the pipeline's
own physics band ``rate_scales`` (its 5/95 % wear-clock factors). That band was calibrated against Monte Carlo
runs of the damage law; when it was calibrated with the rate scale s in the law (``band_includes_rate_scale``),
the s share is taken out in quadrature (sigma_eps^2 = sigma_band^2 - sigma_s^2) so that s, which the
particles carry, is not counted twice.
"""

from __future__ import annotations

import math
from typing import Any

import torch

from .damage_law import DamageLaw
from .measurement import Z95

HUGE = 1e30     # the RUL of a particle still healthy at the end of its search (censored)


def eps_log_sigmas(model: Any, law: DamageLaw, band_includes_rate_scale: bool) -> tuple[float, float]:
    """(sigma_low, sigma_high) of log r from the pipeline's ``rate_scales`` (s_5 >= s_50 >= s_95 of the RUL
    5/50/95 %): RUL 5 % = RUL / s_5, so log r has its 95 % quantile at log(s_5 / s_50) and its 5 % at
    log(s_95 / s_50)."""
    scales = model.rate_scales.to(torch.float64)
    hi = max(math.log(float(scales[0] / scales[1])), 0.0) / Z95
    lo = max(-math.log(float(scales[2] / scales[1])), 0.0) / Z95
    if band_includes_rate_scale:
        s2 = law.rate_scale_sigma ** 2
        hi, lo = math.sqrt(max(hi * hi - s2, 0.0)), math.sqrt(max(lo * lo - s2, 0.0))
    return lo, hi


class ParticleRUL:
    """Per-particle RUL with the pipeline's health classifier.

    Args:
        model: the exported pipeline (``classifier`` with its ``threshold``, ``times``).
        law: the damage law (F, k0, horizon).
        max_rate_scale: largest s r the wear-clock search covers (the grid reaches horizon x this).
        bisections: halvings of the first faulty coarse interval.
        eps_sigmas: (low, high) log-std of the future-eps factor r (:func:`eps_log_sigmas`); (0, 0): none.
    """

    def __init__(self, model: Any, law: DamageLaw, max_rate_scale: float = 8.0, bisections: int = 6,
                 eps_sigmas: tuple[float, float] = (0.0, 0.0)):
        if not max_rate_scale >= 1.0:
            raise ValueError(f"max_rate_scale must be >= 1, got {max_rate_scale!r}")
        self.model, self.law = model, law
        self.step = float(model.times[1] - model.times[0])
        self.horizon = law.horizon_hours
        n = math.ceil(self.horizon * max_rate_scale / self.step)
        t = torch.arange(n + 1, dtype=torch.float64) * self.step
        self.propagators = torch.linalg.matrix_exp(law.rate * t.view(-1, 1, 1))        # (n + 1, 8, 8)
        self.bisections = int(bisections)
        self.eps_sigmas = (float(eps_sigmas[0]), float(eps_sigmas[1]))
        self.threshold = model.classifier.threshold

    def score(self, k: torch.Tensor) -> torch.Tensor:
        """f(k) - threshold (N,) of fault vectors (N, 8), clamped to [0, 1] as the pipeline does; > 0 healthy."""
        with torch.no_grad():
            return (self.model.classifier(k.clamp(0.0, 1.0)) - self.threshold).to(torch.float64)

    def eps_factors(self, z: torch.Tensor) -> torch.Tensor:
        """Wear-clock factors r = exp(sigma z) of standard normals z (any shape), two-piece sigma."""
        lo, hi = self.eps_sigmas
        return torch.exp(torch.where(z > 0, hi * z, lo * z))

    def _at(self, dk: torch.Tensor, tau: torch.Tensor) -> torch.Tensor:
        """k0 + expm(tau F) dk for per-row wear-clock times tau (N,) [h], dk (N, 8)."""
        j = torch.div(tau, self.step, rounding_mode="floor").long().clamp(max=self.propagators.shape[0] - 1)
        short = self.law.propagate(dk, tau - j.to(tau) * self.step)
        return self.law.nominal + (self.propagators[j] @ short.unsqueeze(-1)).squeeze(-1)

    def wear_clock_crossing(self, k: torch.Tensor, tau_max: float) -> torch.Tensor:
        """tau* (N,) [h]: first wear-clock time at which f says faulty, from k (N, 8); 0 if already faulty,
        ``HUGE`` if still healthy at ``tau_max``."""
        n_grid = self.propagators.shape[0] - 1
        last = min(n_grid, math.ceil(tau_max / self.step))
        idx = [0] + [2 ** i for i in range(max(1, math.ceil(math.log2(max(last, 1)))) + 1) if 2 ** i < last] + [last]
        idx = torch.tensor(sorted(set(idx)))
        dk = (k - self.law.nominal).to(torch.float64)
        traj = self.law.nominal + torch.einsum("tij,nj->tni", self.propagators[idx], dk)   # (C, N, 8)
        c, n = traj.shape[0], k.shape[0]
        score = self.score(traj.reshape(-1, 8)).reshape(c, n)
        faulty = score <= 0
        any_faulty = faulty.any(0)
        first = torch.argmax(faulty.to(torch.int64), dim=0)
        prev = (first - 1).clamp(min=0)
        times = idx.to(torch.float64) * self.step
        lo, hi = times[prev], times[first]
        s0, s1 = score.gather(0, prev.unsqueeze(0))[0], score.gather(0, first.unsqueeze(0))[0]
        for _ in range(self.bisections):
            mid = 0.5 * (lo + hi)
            s_mid = self.score(self._at(dk, mid))
            bad = s_mid <= 0
            hi, s1 = torch.where(bad, mid, hi), torch.where(bad, s_mid, s1)
            lo, s0 = torch.where(bad, lo, mid), torch.where(bad, s0, s_mid)
        frac = (s0 / (s0 - s1).clamp(min=1e-12)).clamp(0.0, 1.0)
        crossing = torch.where(first > 0, lo + frac * (hi - lo), torch.zeros_like(lo))
        return torch.where(any_faulty, crossing, torch.full_like(crossing, HUGE))

    def __call__(self, k: torch.Tensor, s: torch.Tensor, z_eps: torch.Tensor | None = None
                 ) -> tuple[torch.Tensor, torch.Tensor]:
        """RUL 5/50/95 % of particle clouds: k (B, M, 8), s (B, M), standard normals z_eps (B, M) for the
        future-eps factor (None: none). Returns (quantiles (B, 3) [h], NaN where censored; censored (B, 3))."""
        b, m = s.shape
        speed = s.to(torch.float64) * (1.0 if z_eps is None else self.eps_factors(z_eps.to(torch.float64)))
        tau_max = self.horizon * float(speed.max()) if speed.numel() else self.horizon
        tau = self.wear_clock_crossing(k.reshape(-1, 8), tau_max).reshape(b, m)
        rul = torch.where(tau >= HUGE, torch.full_like(tau, HUGE), tau / speed)
        q = torch.quantile(rul, torch.tensor([0.05, 0.5, 0.95], dtype=rul.dtype), dim=1).T        # (B, 3)
        censored = q >= self.horizon
        return torch.where(censored, torch.full_like(q, float("nan")), q), censored
