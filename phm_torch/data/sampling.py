"""Importance sampling of fault vectors: the seed paper's scaled Latin hypercube.

A Latin hypercube J in [0, 1)^(n x 8) (``scipy.stats.qmc.LatinHypercube``) is mapped about the
nominal vector k_0 so that the normalised L-infinity distance from nominal is uniformly distributed
(paper: K_ij = J_ij ** n_r, n_r = number of rescaled parameters). Per parameter i:

* k_0,i = 0 (a damage, nominal at the lower bound): k_i = r * J_i ** n_r;
* k_0,i = 1: k_i = 1 - r * J_i ** n_r;
* 0 < k_0,i < 1 (k8, gain drift, nominal 0.5): two-sided, u = |2 J_i - 1| is uniform on [0, 1] and
  k_i = k_0,i + r * (1 - k_0,i) * u ** n_r above nominal (J_i >= 0.5), k_0,i - r * k_0,i * u ** n_r below;
* parameters listed as ``uniform`` (k7, the eccentricity phase): k_i = J_i, not rescaled.

With d_i = |k_i - k_0,i| / (reach of parameter i on that side) the normalised distance
d = max_i d_i = r * max_i u_i ** n_r, and P(d <= a) = P(max_i u_i <= (a/r) ** (1/n_r)) = a / r:
uniform on [0, r]. ``radius`` r < 1 restricts the domain to the neighbourhood of nominal (the paper's
RUL validation set).

``distance_exponent`` q generalises the paper's scaling radially: each paper vector's deviation from
nominal is scaled by d' / d with d' = r (d / r) ** (1/q), so that P(d' <= a) = (a/r) ** q. q = 1 is the
paper's (d uniform); q > 1 moves the samples away from nominal (fewer healthy actuators), q < 1 towards
it. The direction of the deviation keeps the paper's law: given max_i u_i = m, the other u_i are uniform
on [0, m], so the normalised deviations d_i / d = (u_i / m) ** n_r do not depend on d, and P(healthy | d)
is the same function whatever q (changing the exponent of every parameter instead would change the
direction too: measured, a calibration built on that assumption missed its target 0.3 by 0.26).
``calibration.py`` chooses q so that a configured fraction of the sampled actuators is healthy.

``near_nominal_share`` s keeps a floor under the density near nominal when q > 1 moves the samples out:
P(d' <= a) = s (a/r) + (1 - s) (a/r) ** q, the mixture of the paper's scaling (weight s) and exponent q,
reached by the same radial map with d' = r F^-1(d / r) (monotone, so the Latin hypercube's strata and the
directions are kept). Without it, a robust actuator (its faults leave it healthy far out) pushed q to its
bound and its store to 0.1 % of the vectors within a tenth of the radius: its pipeline then read new
actuators high, and its own verdict called 14 % of healthy inspections faulty (5 % with the floor;
docs/dataset.md).
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from scipy.stats import qmc

from ..faults import N_FAULTS


@dataclass(frozen=True)
class ImportanceSampler:
    """Scaled Latin hypercube about ``nominal``.

    Attributes:
        nominal: k_0, 8 values in [0, 1].
        uniform: 0-based indices of the parameters left uniform on [0, 1] (k7 -> index 6).
        radius: r in (0, 1], the largest normalised distance from nominal.
        distance_exponent: q > 0, P(d <= a) = (a / r) ** q (1: the paper's scaling, d uniform).
        near_nominal_share: s in [0, 1), the weight of the paper's scaling in the radial law
            P(d <= a) = s (a / r) + (1 - s) (a / r) ** q (0: exponent q alone).
    """

    nominal: tuple[float, ...]
    uniform: tuple[int, ...]
    radius: float
    distance_exponent: float = 1.0
    near_nominal_share: float = 0.0

    def __post_init__(self) -> None:
        nominal = tuple(float(v) for v in self.nominal)
        object.__setattr__(self, "nominal", nominal)
        object.__setattr__(self, "uniform", tuple(int(i) for i in self.uniform))
        if len(nominal) != N_FAULTS or any(not 0.0 <= v <= 1.0 for v in nominal):
            raise ValueError(f"sampling.nominal must be {N_FAULTS} values in [0, 1], got {list(nominal)}")
        bad = [i for i in self.uniform if not 0 <= i < N_FAULTS]
        if bad or len(set(self.uniform)) != len(self.uniform):
            raise ValueError(
                f"sampling.uniform must be distinct indices in [0, {N_FAULTS - 1}], got {list(self.uniform)}"
            )
        if self.n_rescaled < 1:
            raise ValueError("sampling.uniform: at least one parameter must be rescaled")
        if not (math.isfinite(self.radius) and 0.0 < self.radius <= 1.0):
            raise ValueError(f"sampling.radius must be in (0, 1], got {self.radius}")
        q = self.distance_exponent
        if isinstance(q, bool) or not isinstance(q, (int, float)) or not (math.isfinite(q) and q > 0):
            raise ValueError(f"sampling.distance_exponent must be a number > 0, got {q!r}")
        share = self.near_nominal_share
        if isinstance(share, bool) or not isinstance(share, (int, float)) or not 0.0 <= share < 1.0:
            raise ValueError(f"sampling.near_nominal_share must be in [0, 1), got {share!r}")

    @classmethod
    def from_record(
        cls, sampling: Mapping[str, Any] | None, nominal: Sequence[float], uniform: Sequence[int]
    ) -> ImportanceSampler:
        """The full-domain sampler (radius 1) of a store from its calibration record (``calibration.py``: its
        ``sampling.json``, the manifest's ``sampling``): its exponent and applied near-nominal share; None, or a
        record from before the share, reads as the paper's scaling and no share."""
        record = sampling or {}
        return cls(
            tuple(nominal),
            tuple(uniform),
            1.0,
            float(record.get("distance_exponent", 1.0)),
            float(record.get("near_nominal_share", 0.0)),
        )

    @property
    def rescaled(self) -> tuple[int, ...]:
        """0-based indices of the rescaled parameters."""
        return tuple(i for i in range(N_FAULTS) if i not in self.uniform)

    @property
    def n_rescaled(self) -> int:
        """n_r, the number of rescaled parameters (the paper's exponent of the rescaling)."""
        return len(self.rescaled)

    def sample(self, n: int, seed: int | np.random.SeedSequence) -> np.ndarray:
        """n fault vectors (n, 8) float64; deterministic in ``seed``."""
        if isinstance(n, bool) or not isinstance(n, int) or n < 1:
            raise ValueError(f"number of samples must be an integer >= 1, got {n!r}")
        rng = np.random.default_rng(seed)
        j = qmc.LatinHypercube(d=N_FAULTS, rng=rng).random(n)
        return self.rescale(j)

    def rescale(self, j: np.ndarray) -> np.ndarray:
        """Map points of the unit hypercube J (n, 8) to fault vectors K (n, 8)."""
        j = np.asarray(j, dtype=np.float64)
        k = j.copy()
        p, r = self.n_rescaled, self.radius
        for i in self.rescaled:
            k0 = self.nominal[i]
            if k0 == 0.0:
                k[:, i] = r * j[:, i] ** p
            elif k0 == 1.0:
                k[:, i] = 1.0 - r * j[:, i] ** p
            else:
                u = np.abs(2.0 * j[:, i] - 1.0) ** p
                k[:, i] = np.where(j[:, i] >= 0.5, k0 + r * (1.0 - k0) * u, k0 - r * k0 * u)
        k = np.clip(k, 0.0, 1.0)
        q, share = self.distance_exponent, self.near_nominal_share
        if q != 1.0:  # radial remapping d -> r F^-1(d / r), with F the radial law's distribution function
            d = self.distance(k)
            if share == 0.0:  # F(a) = a ** q, inverted in closed form
                scale = np.where(d > 0, (d / r) ** (1.0 / q - 1.0), 1.0)
            else:
                scale = np.where(d > 0, radial_quantile(d / r, q, share) / np.where(d > 0, d / r, 1.0), 1.0)
            cols = list(self.rescaled)
            k0 = np.asarray(self.nominal)[cols]
            k[:, cols] = np.clip(k0 + (k[:, cols] - k0) * scale[:, None], 0.0, 1.0)
        return k

    def distance(self, k: np.ndarray | Sequence[Sequence[float]]) -> np.ndarray:
        """Normalised L-infinity distance from nominal (n,) of fault vectors (n, 8), over the rescaled
        parameters, each divided by its reach on its side of nominal."""
        k = np.asarray(k, dtype=np.float64)
        out = np.zeros(k.shape[0])
        for i in self.rescaled:
            k0 = self.nominal[i]
            d = k[:, i] - k0
            reach = np.where(d >= 0, 1.0 - k0, k0)
            out = np.maximum(out, np.abs(d) / np.where(reach > 0, reach, 1.0))
        return out


def radial_cdf(a: np.ndarray | float, exponent: float, share: float = 0.0) -> np.ndarray:
    """F(a) = s a + (1 - s) a ** q: P(d <= a r) under the sampler's radial law, a in [0, 1]."""
    a = np.asarray(a, dtype=np.float64)
    return share * a + (1.0 - share) * a**exponent


def radial_quantile(u: np.ndarray, exponent: float, share: float) -> np.ndarray:
    """F^-1(u) of :func:`radial_cdf` (u (n,) in [0, 1]), by bisection: F is increasing from F(0) = 0 to F(1) = 1.
    60 halvings bring the bracket below 1e-18, under float64's resolution of a."""
    u = np.asarray(u, dtype=np.float64)
    lo, hi = np.zeros_like(u), np.ones_like(u)
    for _ in range(60):
        mid = 0.5 * (lo + hi)
        below = radial_cdf(mid, exponent, share) < u
        lo, hi = np.where(below, mid, lo), np.where(below, hi, mid)
    return 0.5 * (lo + hi)
