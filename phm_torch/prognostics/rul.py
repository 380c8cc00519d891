"""Remaining useful life: propagate damage until the health score says "faulty" (seed paper, RUL section).

Every sample gets its own RUL: the health score is evaluated on the whole integration grid, the first
grid interval where it turns negative is located per sample, and the crossing is refined inside that
interval by bisection, each sample re-integrating from its own grid state over its own sub-interval
(time rescaled per sample so one batched torchdiffeq call serves all samples).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import torch
from torchdiffeq import odeint

from .damage import DamageModel

# Health score convention: f(k) > 0 healthy, f(k) <= 0 faulty; input (N, 8), output (N,).
HealthScore = Callable[[torch.Tensor], torch.Tensor]
QUANTILES = (0.05, 0.50, 0.95)
_Z = {q: math.sqrt(2.0) * torch.erfinv(torch.tensor(2 * q - 1.0, dtype=torch.float64)).item() for q in QUANTILES}


@dataclass
class RULEstimate:
    """RUL statistics per sample, hours; each tensor (B,) unless noted.

    Attributes:
        gaussian: (B, 3) 5/50/95 % RUL from a normal fit over the Monte Carlo runs (the paper's method).
        empirical: (B, 3) empirical 5/50/95 % quantiles.
        mean, std: of the Monte Carlo RULs.   censored: fraction of runs reaching the horizon healthy.
        samples: (B, n) the Monte Carlo RULs.
    """

    gaussian: torch.Tensor
    empirical: torch.Tensor
    mean: torch.Tensor
    std: torch.Tensor
    censored: torch.Tensor
    samples: torch.Tensor


class RULEstimator:
    """RUL from an initial fault vector, a damage model and a health score.

    Args:
        damage: the propagation model.
        score: health score f(k) (N, 8) -> (N,), positive = healthy (e.g. the surrogate classifier or,
            for reference RULs, the true assessment function).
        n_samples: Monte Carlo runs per initial vector.
        refine_iterations: bisection steps inside the crossing interval (step / 2^n resolution).
    """

    def __init__(
        self,
        damage: DamageModel,
        score: HealthScore,
        n_samples: int = 200,
        refine_iterations: int = 12,
        coarse: int = 8,
    ):
        if n_samples < 2:
            raise ValueError(f"rul.n_samples must be >= 2, got {n_samples}")
        if refine_iterations < 0:
            raise ValueError(f"rul.refine_iterations must be >= 0, got {refine_iterations}")
        if isinstance(coarse, bool) or not isinstance(coarse, int) or coarse < 1:
            raise ValueError(f"rul.coarse must be an integer >= 1, got {coarse!r}")
        self.damage, self.score = damage, score
        self.n_samples, self.refine_iterations, self.coarse = n_samples, refine_iterations, coarse

    def _scores(self, k: torch.Tensor, chunk: int = 65536) -> torch.Tensor:
        flat = k.reshape(-1, k.shape[-1]).clamp(0.0, 1.0)  # the score is defined on the unit cube
        # chunks bound the memory of kernel features (a Monte Carlo batch is ~10^7 points)
        out = torch.cat([self.score(flat[i : i + chunk]) for i in range(0, flat.shape[0], chunk)])
        return out.reshape(k.shape[:-1])

    def first_crossing(
        self, k0: torch.Tensor, eps: torch.Tensor | None = None, scale: torch.Tensor | None = None
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Time [h] of the first healthy -> faulty transition per sample, and whether it was censored.

        Args:
            k0: (B, 8) initial fault vectors.   eps: (B, n_blocks, 8) rate noise, or None.
            scale: (B,) wear-rate scales s, or None (s = 1).
        Returns:
            (rul (B,), censored (B,) bool). Already-faulty samples get 0; samples still healthy at the
            horizon get the horizon and ``censored = True``.
        """
        d = self.damage
        t = d.grid
        traj = d.integrate(k0, eps, scale=scale)  # (T, B, 8)
        first, any_faulty = self._first_faulty_index(traj)
        rul = torch.where(any_faulty, t[first], torch.full_like(t[first], d.horizon))
        inside = any_faulty & (first > 0)
        if inside.any() and self.refine_iterations:
            b = inside.nonzero().flatten()
            start = traj[first[b] - 1, b]  # (n, 8) last healthy grid state
            t_start = t[first[b] - 1]
            e = eps[b] if eps is not None else None
            sc = scale[b] if scale is not None else None
            lo = torch.zeros(b.numel(), dtype=torch.float64)
            hi = torch.full_like(lo, d.step)
            for _ in range(self.refine_iterations):
                mid = 0.5 * (lo + hi)
                k_mid = self._advance(start, t_start, mid, e, sc)
                bad = self._scores(k_mid) <= 0
                hi = torch.where(bad, mid, hi)
                lo = torch.where(bad, lo, mid)
            rul[b] = t_start + hi
        return rul, ~any_faulty

    def _first_faulty_index(self, traj: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """First faulty grid index per trajectory (T, B, 8) -> (index (B,), any faulty (B,) bool).

        The score is evaluated every ``coarse`` grid points, then on the grid points of the first faulty
        coarse interval only (the score is the costly part: ~``coarse`` times fewer calls). A trajectory
        that turns faulty and healthy again between two coarse points is missed; the damage grows
        monotonically, so only a classifier ripple narrower than ``coarse`` steps could do that.
        """
        n_t, b = traj.shape[0], traj.shape[1]
        grid = torch.arange(0, n_t, self.coarse)
        if int(grid[-1]) != n_t - 1:
            grid = torch.cat([grid, torch.tensor([n_t - 1])])
        faulty_c = self._scores(traj[grid]) <= 0  # (Tc, B)
        any_faulty = faulty_c.any(0)
        first_c = faulty_c.float().argmax(0)
        first = torch.where(any_faulty, grid[first_c], torch.full((b,), n_t - 1, dtype=torch.long))
        inside = (any_faulty & (first_c > 0)).nonzero().flatten()
        if inside.numel() and self.coarse > 1:
            lo = grid[first_c[inside] - 1]  # last healthy coarse point
            width = int((grid[first_c[inside]] - lo).max())
            idx = (lo.unsqueeze(1) + torch.arange(1, width + 1)).clamp(max=n_t - 1)  # (n, width)
            window = traj[idx, inside.unsqueeze(1)]  # (n, width, 8)
            bad = self._scores(window) <= 0
            bad |= idx >= grid[first_c[inside]].unsqueeze(1)  # the faulty coarse point itself
            first[inside] = idx.gather(1, bad.float().argmax(1, keepdim=True)).squeeze(1)
        return first, any_faulty

    def _advance(
        self,
        k: torch.Tensor,
        t0: torch.Tensor,
        tau: torch.Tensor,
        eps: torch.Tensor | None,
        scale: torch.Tensor | None = None,
    ) -> torch.Tensor:
        """k after a per-sample time tau from per-sample start t0 (wear-rate scale per sample, or None):
        one batched odeint on rescaled time."""
        f, k_nom, block = self.damage.rate, self.damage.nominal, self.damage.block
        rate = None
        if eps is not None:
            i = torch.clamp((t0 / block).floor().long(), max=eps.shape[1] - 1)
            rate = eps[torch.arange(eps.shape[0]), i]  # constant within the grid step

        def rhs(s: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
            dy = (y - k_nom) @ f.T
            if scale is not None:
                dy = dy * scale.unsqueeze(-1)
            if rate is not None:
                dy = dy + rate
            return dy * tau.unsqueeze(-1)

        s = torch.tensor([0.0, 1.0], dtype=torch.float64)
        return odeint(rhs, k, s, method="rk4", options={"step_size": 0.25})[-1]

    def estimate(self, k0: torch.Tensor, generator: torch.Generator | None = None) -> RULEstimate:
        """Monte Carlo over eps and the wear-rate scale s (one s per run: a run is one possible actuator):
        RUL 5/50/95 % per initial vector, Gaussian fit and empirical quantiles.

        eps is drawn first, then s (nothing when ``rate_scale_sigma`` is 0), so the eps of a seed do not
        depend on the rate-scale setting.
        """
        k0 = torch.as_tensor(k0, dtype=torch.float64)
        b, n = k0.shape[0], self.n_samples
        eps = self.damage.sample_noise(b * n, generator)
        scale = self.damage.sample_rate_scale(b * n, generator) if self.damage.rate_scale_sigma > 0 else None
        rul, censored = self.first_crossing(k0.repeat_interleave(n, 0), eps, scale)
        rul, censored = rul.view(b, n), censored.view(b, n)
        mean, std = rul.mean(1), rul.std(1)
        gauss = torch.stack([(mean + _Z[q] * std).clamp(min=0.0) for q in QUANTILES], dim=1)
        emp = torch.quantile(rul, torch.tensor(QUANTILES, dtype=torch.float64), dim=1).T
        return RULEstimate(gauss, emp, mean, std, censored.double().mean(1), rul)


def ordered_bounds(rul: torch.Tensor) -> torch.Tensor:
    """The deterministic variant's RULs (B, 3) for delta_5, delta_50, delta_95 -> (B, 3) bounds.

    The 5 % / 95 % bounds are the shortest / longest of the three disturbed propagations, the median
    stays the delta_50 one: a component whose effect on health changes sign along the way (the gain drift
    k8 raises the bandwidth but lowers the gain margin; couplings in F) can make the "less damage"
    propagation fail first for some vectors, which would otherwise give an inverted band.
    """
    return torch.stack([rul.amin(-1), rul[..., 1], rul.amax(-1)], dim=-1)


VARIANTS = ("initial_state", "rate")


class DeterministicRUL:
    """Noise-free RUL bounds calibrated on the Monte Carlo quantiles; two variants.

    ``initial_state`` (the paper's): a disturbance delta_q u on k(0) per quantile q. u is the noise
    standard deviation direction (unit max-norm, damage components only); each delta_q is calibrated by
    bisection so that, over a calibration set, the median ratio of the deterministic RUL to the Monte
    Carlo q-quantile RUL is 1. Three noise-free propagations.

    ``rate``: the median as above (delta_50 on k(0)); the bounds scale the wear *rate*: F -> s_q F. The
    damage ODE is linear, so without noise k(t; s F) = k(s t; F) and the bound is exactly RUL_50 / s_q:
    one propagation, and a band that cannot collapse. The initial-state band does collapse where the
    health score is not monotone along u (less damage on a shorted phase can fail as soon or sooner):
    on the paper run its upper bound equals its median for ~10 % of the vectors. s_q is the median over
    the calibration set of RUL_50 / (Monte Carlo q-quantile RUL): the physics noise acts as a spread of
    the wear clock. The Monte Carlo runs draw the per-actuator wear-rate scale too (``rate_scale_sigma``
    of the damage model), so both variants' bands are calibrated to cover it as well as eps.

    Args:
        estimator: the Monte Carlo estimator (its damage model and score are reused).
        variant: ``"initial_state"`` or ``"rate"``.
    """

    def __init__(self, estimator: RULEstimator, variant: str = "initial_state"):
        if variant not in VARIANTS:
            raise ValueError(f"rul.band must be one of {VARIANTS}, got {variant!r}")
        sd = estimator.damage.noise_std
        self.estimator, self.variant = estimator, variant
        self.direction = sd / sd.max().clamp(min=1e-300)
        self.deltas_: torch.Tensor | None = None
        self.scales_: torch.Tensor | None = None
        self.saturated_: list[bool] = []

    def disturbed(self, k0: torch.Tensor, delta: torch.Tensor | float) -> torch.Tensor:
        """k0 (B, 8) with its damage |k - k_nom| changed by delta u per component, never past nominal.

        delta (scalar or (B,)) > 0 adds damage, < 0 removes it. The damage of the two-sided gain drift k8 is
        |k8 - 0.5|, so the disturbance points away from nominal per sample; removing damage stops at nominal
        instead of crossing it (a crossed k8 would drift the other way and fail *sooner*, inverting the band).
        """
        nominal = self.estimator.damage.nominal.to(k0)
        dev = k0 - nominal
        side = torch.where(dev >= 0, 1.0, -1.0).to(k0.dtype)
        delta = torch.as_tensor(delta, dtype=k0.dtype)
        step = delta.reshape(-1, 1) if delta.ndim else delta
        return nominal + side * (dev.abs() + step * self.direction.to(k0)).clamp(min=0.0)

    def rul(self, k0: torch.Tensor, delta: torch.Tensor | float) -> torch.Tensor:
        """Noise-free RUL [h] (B,) from k0 disturbed by delta (see :meth:`disturbed`)."""
        return self.estimator.first_crossing(self.disturbed(k0, delta))[0]

    def calibrate(
        self,
        k_calib: torch.Tensor,
        generator: torch.Generator | None = None,
        iterations: int = 30,
        bracket: float = 0.05,
    ) -> torch.Tensor:
        """Find delta_5, delta_50, delta_95 (fitted to ``deltas_``, (3,)) and the rate scales s_5, 1, s_95
        (``scales_``, (3,)) on calibration vectors (N, 8).

        ``bracket`` bounds |delta| (in units of the damage k); ``saturated_`` records, per quantile,
        whether the bisection ended on the bracket (the target RUL not reachable within it).
        """
        mc = self.estimator.estimate(k_calib, generator).empirical  # (N, 3)
        usable = mc[:, 1] > 0
        if not usable.any():
            raise ValueError("rul calibration: every calibration vector is already faulty")
        k, target = k_calib[usable], mc[usable]
        deltas = []
        for j in range(len(QUANTILES)):
            lo, hi = -bracket, bracket  # larger delta = more damage = shorter RUL
            for _ in range(iterations):
                mid = 0.5 * (lo + hi)
                ratio = (self.rul(k, mid) / target[:, j].clamp(min=1e-9)).median()
                if ratio > 1:
                    lo = mid
                else:
                    hi = mid
            deltas.append(0.5 * (lo + hi))
        self.deltas_ = torch.tensor(deltas, dtype=torch.float64)
        self.saturated_ = [bool(abs(abs(d) - bracket) < 1e-6 * bracket) for d in deltas]
        median = self.rul(k, deltas[1])
        inside = (median > 0) & (median < self.estimator.damage.horizon)  # censored medians say nothing
        if not inside.any():
            raise ValueError("rul calibration: no calibration vector fails within the horizon")
        self.scales_ = torch.stack(
            [(median[inside] / target[inside, j].clamp(min=1e-9)).median() for j in range(len(QUANTILES))]
        ).to(torch.float64)
        self.scales_[1] = 1.0
        return self.deltas_

    def pipeline_parameters(self, variant: str | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        """(deltas (3,), rate scales (3,)) of ``variant`` (default: this one's), as
        :class:`~phm_torch.online.OnlinePipeline` takes them: initial_state = (delta_q, ones),
        rate = (delta_50 three times, s_q)."""
        if self.deltas_ is None or self.scales_ is None:
            raise ValueError("DeterministicRUL: call calibrate() first")
        variant = self.variant if variant is None else variant
        if variant not in VARIANTS:
            raise ValueError(f"rul.band must be one of {VARIANTS}, got {variant!r}")
        if variant == "rate":
            return self.deltas_[1].repeat(3), self.scales_.clone()
        return self.deltas_.clone(), torch.ones(3, dtype=torch.float64)

    def predict(self, k0: torch.Tensor) -> torch.Tensor:
        """RUL 5/50/95 % [h] (B, 3) of the variant (5 % = most damage); the rate bounds stop at the horizon."""
        deltas, scales = self.pipeline_parameters()
        if self.variant == "rate":
            median = self.rul(k0, float(deltas[1]))
            rul = (median.unsqueeze(1) / scales).clamp(max=self.estimator.damage.horizon)
        else:
            rul = torch.stack([self.rul(k0, float(d)) for d in deltas], dim=1)
        return ordered_bounds(rul)
