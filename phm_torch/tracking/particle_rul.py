"""RUL of posterior particles: each particle (k, s) propagated noise-free until the pipeline's health classifier
f turns faulty, then 5/50/95 % over the particles.

The noise-free solution with rate scale s is k(t; sF) = k(st; F): one search on the wear clock tau = s t gives
tau*(k), and the particle's RUL is tau* / s. A particle whose previous crossing is known (the tracker carries
it: between inspections the wear clock moves by s dt and the noise barely moves the crossing) is searched in a
bracket of +/- ``WARM_WIDTH`` around tau*_prev - s dt: two scores check the bracket, then ``REFINE``
Illinois (regula falsi) steps and a final interpolation of the score's zero (5 classifier rows instead of
~18). The others, and a bracket that does not hold the crossing, run the cold search: a geometric coarse
grid of the wear clock (0, dt, 2 dt, 4 dt, ...; dt the pipeline's grid step), ``bisections`` halvings of the
first faulty interval and the same interpolation. Off-grid points are :meth:`DamageLaw.propagate`.

Future eps (the rate disturbance after the last inspection) widens the band beyond the (k, s) posterior: each
particle's wear clock is sped up by a factor r, lognormal with a two-piece log-std fitted to the pipeline's
own physics band ``rate_scales`` (its 5/95 % wear-clock factors). That band was calibrated against Monte Carlo
runs of the damage law; when it was calibrated with the rate scale s in the law (``band_includes_rate_scale``),
the s share is taken out in quadrature (sigma_eps^2 = sigma_band^2 - sigma_s^2) so that s, which the
particles carry, is not counted twice.
"""

from __future__ import annotations

import logging
import math
from typing import Any

import torch

from .damage_law import DamageLaw
from .measurement import Z95

log = logging.getLogger(__name__)

HUGE = 1e30  # the RUL of a particle still healthy at the end of its search (censored)
WARM_WIDTH = 0.1  # relative half-width of the warm bracket (at least one grid step)
REFINE = 2  # Illinois steps in a warm bracket
MIN_LIVE_RUL = 1e-3  # [h] a healthy particle's RUL after its boundary timing error: still healthy (> 0)


def eps_log_sigmas(model: Any, law: DamageLaw, band_includes_rate_scale: bool) -> tuple[float, float]:
    """(sigma_low, sigma_high) of log r from the pipeline's ``rate_scales`` (s_5 >= s_50 >= s_95 of the RUL
    5/50/95 %): RUL 5 % = RUL / s_5, so log r has its 95 % quantile at log(s_5 / s_50) and its 5 % at
    log(s_95 / s_50). A band said to include s but narrower than s's own spread cannot: it is read as eps alone
    (with a warning), rather than leaving no future eps at all."""
    scales = model.rate_scales.to(torch.float64)
    hi = max(math.log(float(scales[0] / scales[1])), 0.0) / Z95
    lo = max(-math.log(float(scales[2] / scales[1])), 0.0) / Z95
    if band_includes_rate_scale:
        s = law.rate_scale_sigma
        if min(hi, lo) < s:
            log.warning(
                "the pipeline's RUL band (log-std %.3g / %.3g) is narrower than the wear-rate scale's "
                "spread (%.3g) it is said to include: read as eps alone",
                lo,
                hi,
                s,
            )
        else:
            hi, lo = math.sqrt(hi * hi - s * s), math.sqrt(lo * lo - s * s)
    return lo, hi


class ParticleRUL:
    """Per-particle RUL with the pipeline's health classifier.

    Args:
        model: the exported pipeline (``classifier`` with its ``threshold``, ``times``).
        law: the damage law (F, k0, horizon).
        max_rate_scale: largest s r the wear-clock search covers (the grid reaches horizon x this).
        bisections: halvings of the first faulty coarse interval.
        eps_sigmas: (low, high) log-std of the future-eps factor r (:func:`eps_log_sigmas`); (0, 0): none.
        boundary_std_hours: std [h] of the health classifier's crossing time against the true boundary's (phi_a's)
            along a damage path: each particle still healthy and not censored gets that much Gaussian timing
            error in its RUL, kept above 0 (a particle's being past the boundary, and so the end-of-life flag, is
            unchanged); 0: none.
    """

    def __init__(
        self,
        model: Any,
        law: DamageLaw,
        max_rate_scale: float = 8.0,
        bisections: int = 6,
        eps_sigmas: tuple[float, float] = (0.0, 0.0),
        boundary_std_hours: float = 0.0,
    ):
        if not max_rate_scale >= 1.0:
            raise ValueError(f"max_rate_scale must be >= 1, got {max_rate_scale!r}")
        if not (math.isfinite(boundary_std_hours) and boundary_std_hours >= 0.0):
            raise ValueError(f"tracker.boundary_std_hours must be finite and >= 0, got {boundary_std_hours!r}")
        self.boundary_std = float(boundary_std_hours)
        self.model, self.law = model, law
        self.step = float(model.times[1] - model.times[0])
        self.horizon = law.horizon_hours
        n = math.ceil(self.horizon * max_rate_scale / self.step)
        t = torch.arange(n + 1, dtype=torch.float64) * self.step
        self.propagators = torch.linalg.matrix_exp(law.rate * t.view(-1, 1, 1))  # (n + 1, 8, 8)
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
        return self.law.nominal + self.law.propagate(dk, tau)

    def warm_crossing(self, k: torch.Tensor, guess: torch.Tensor, tau_max: torch.Tensor) -> torch.Tensor:
        """tau* (N,) [h] as :meth:`wear_clock_crossing`, searched near ``guess`` (N,) (NaN: unknown; ``HUGE``:
        healthy beyond the search); ``tau_max`` (N,) the per-row end of the search. Rows whose bracket does not
        hold the crossing fall back to the cold search."""
        dk = (k - self.law.nominal).to(torch.float64)
        out = torch.full_like(guess, float("nan"))
        # already faulty: no life left, whatever the path does later. The score need not stay faulty along it
        # (phi_a's bandwidth can come back above its limit), and a bracket further on would find a later crossing
        out[self.score(k) <= 0] = 0.0
        far = (guess >= HUGE) & torch.isnan(out)
        if bool(far.any()):  # still healthy at the end of its own search: 1 row
            i = far.nonzero().flatten()
            healthy = self.score(self._at(dk[i], tau_max[i])) > 0
            out[i[healthy]] = HUGE
        near = torch.isfinite(guess) & (guess < HUGE) & torch.isnan(out)
        if bool(near.any()):
            i = near.nonzero().flatten()
            g = guess[i].clamp(min=0.0)
            width = (WARM_WIDTH * g).clamp(min=self.step)
            lo, hi = (g - width).clamp(min=0.0), torch.minimum(g + width, tau_max[i])
            both = self.score(self._at(dk[i].repeat(2, 1), torch.cat([lo, hi])))
            s0, s1 = both[: i.numel()], both[i.numel() :]
            ok = (s0 > 0) & (s1 <= 0)
            if bool(ok.any()):
                j = ok.nonzero().flatten()
                out[i[j]] = self._refine(dk[i[j]], lo[j], hi[j], s0[j], s1[j], REFINE)
        cold = torch.isnan(out)
        if bool(cold.any()):
            i = cold.nonzero().flatten()
            out[i] = self.wear_clock_crossing(k[i], float(tau_max[i].max()))
        return out

    def _refine(
        self, dk: torch.Tensor, lo: torch.Tensor, hi: torch.Tensor, s0: torch.Tensor, s1: torch.Tensor, steps: int
    ) -> torch.Tensor:
        """Zero of the score between lo (healthy, s0 > 0) and hi (faulty, s1 <= 0): Illinois regula falsi (the
        kept end's score halved when the same end is kept twice, so a curved score still converges from both
        sides), then the linear interpolation of the last bracket."""
        side = torch.zeros_like(lo)
        for _ in range(steps):
            frac = (s0 / (s0 - s1).clamp(min=1e-12)).clamp(0.02, 0.98)
            mid = lo + frac * (hi - lo)
            s_mid = self.score(self._at(dk, mid))
            bad = s_mid <= 0
            s0 = torch.where(bad & (side < 0), 0.5 * s0, s0)  # hi moved twice: halve lo's score
            s1 = torch.where(~bad & (side > 0), 0.5 * s1, s1)
            hi, s1 = torch.where(bad, mid, hi), torch.where(bad, s_mid, s1)
            lo, s0 = torch.where(bad, lo, mid), torch.where(bad, s0, s_mid)
            side = torch.where(bad, -torch.ones_like(side), torch.ones_like(side))
        frac = (s0 / (s0 - s1).clamp(min=1e-12)).clamp(0.0, 1.0)
        return lo + frac * (hi - lo)

    def wear_clock_crossing(self, k: torch.Tensor, tau_max: float) -> torch.Tensor:
        """tau* (N,) [h]: first wear-clock time at which f says faulty, from k (N, 8); 0 if already faulty,
        ``HUGE`` if still healthy at ``tau_max``."""
        n_grid = self.propagators.shape[0] - 1
        last = min(n_grid, math.ceil(tau_max / self.step))
        idx = [0] + [2**i for i in range(max(1, math.ceil(math.log2(max(last, 1)))) + 1) if 2**i < last] + [last]
        idx = torch.tensor(sorted(set(idx)))
        dk = (k - self.law.nominal).to(torch.float64)
        traj = self.law.nominal + torch.einsum("tij,nj->tni", self.propagators[idx], dk)  # (C, N, 8)
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

    def __call__(
        self,
        k: torch.Tensor,
        s: torch.Tensor,
        z_eps: torch.Tensor | None = None,
        weights: torch.Tensor | None = None,
        guess: torch.Tensor | None = None,
        faulty_odds: torch.Tensor | None = None,
        z_boundary: torch.Tensor | None = None,
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """RUL 5/50/95 % of particle clouds: k (B, M, 8), s (B, M), standard normals z_eps (B, M) for the
        future-eps factor (None: none), normalised weights (B, M) (None: equal), the particles' previous
        wear-clock crossings moved to now (B, M) (None or NaN: unknown, cold search), standard normals z_boundary
        (B, M) for the boundary's timing error (None: none).

        Returns (quantiles (B, 3) [h], NaN where censored; censored (B, 3); the crossings tau* (B, M) [h])."""
        b, m = s.shape
        speed = s.to(torch.float64) * (1.0 if z_eps is None else self.eps_factors(z_eps.to(torch.float64)))
        tau_max = (self.horizon * speed).reshape(-1)
        guess = torch.full((b * m,), float("nan"), dtype=torch.float64) if guess is None else guess.reshape(-1)
        tau = self.warm_crossing(k.reshape(-1, 8), guess.to(torch.float64), tau_max).reshape(b, m)
        rul = torch.where(tau >= HUGE, torch.full_like(tau, HUGE), tau / speed)
        if z_boundary is not None and self.boundary_std > 0.0:  # where the classifier says it, not where phi_a does
            live = (rul > 0.0) & (rul < HUGE)
            moved = (rul + self.boundary_std * z_boundary.to(rul)).clamp(min=MIN_LIVE_RUL)
            rul = torch.where(live, moved, rul)
        w = torch.full_like(rul, 1.0 / m) if weights is None else weights.to(rul)
        if faulty_odds is not None:
            w = w * torch.where(tau <= 0, faulty_odds.to(rul).unsqueeze(1), torch.ones_like(rul))
            w = w / w.sum(1, keepdim=True).clamp(min=1e-300)
        q = weighted_quantiles(rul, w, (0.05, 0.5, 0.95))  # (B, 3)
        censored = q >= self.horizon
        return torch.where(censored, torch.full_like(q, float("nan")), q), censored, tau


def weighted_quantiles(x: torch.Tensor, w: torch.Tensor, q: tuple[float, ...]) -> torch.Tensor:
    """Quantiles of weighted samples along dim 1: x (B, N, ...) with weights w (B, N) summing to 1 per row ->
    (B, len(q), ...). The inverse of the weighted empirical CDF (the first sorted sample whose cumulative weight
    reaches q): no interpolation, so a quantile is always one of the samples (never between a finite RUL and
    the censored ones)."""
    values, order = torch.sort(x, dim=1)
    ww = w.reshape(w.shape + (1,) * (x.dim() - 2)).expand_as(x)
    cdf = torch.gather(ww, 1, order).cumsum(1)
    cdf = cdf / cdf[:, -1:].clamp(min=1e-300)
    probs = (
        torch.tensor(q, dtype=cdf.dtype)
        .reshape((1, -1) + (1,) * (x.dim() - 2))
        .expand((x.shape[0], len(q)) + tuple(x.shape[2:]))
    )
    idx = torch.searchsorted(cdf.movedim(1, -1).contiguous(), probs.movedim(1, -1).contiguous() - 1e-12)
    idx = idx.clamp(max=x.shape[1] - 1).movedim(-1, 1)
    return torch.gather(values, 1, idx)
