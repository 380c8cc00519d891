"""Importance sampling calibrated to a healthy fraction (``dataset.healthy_fraction``), for any actuator.

The paper's scaling (``sampling.py``, distance exponent q = 1: the normalised distance d from nominal is
uniform) puts ~30 % of the reference actuator's sampled vectors in the healthy class, but another
actuator's assessment can be more or less tolerant of the same normalised damages. The calibration:

1. **Pilot**: ``pilot_size`` vectors with the paper's scaling (d uniform on [0, 1]) from their own seed
   stream (``pilot``, child 5 of ``SeedSequence(seed)``), labelled by the assessment function alone.
2. **Health against distance**: h(d) = P(healthy | d), estimated by a non-increasing step function of d
   (isotonic regression, pool-adjacent-violators: the further from nominal, the less likely healthy).
3. **Exponent**: with P(d <= a) = a^q the expected healthy fraction is H(q) = integral h(d) d(d^q), for
   the step function sum_i h_i (e_{i+1}^q - e_i^q), non-increasing in q; q solves H(q) = target by
   bisection on log q within ``exponent_bounds``.
4. **Keep the paper's** q = 1 when the pilot's own healthy fraction is within ``tolerance`` of the target,
   so that an actuator the paper's scaling already suits (the reference) keeps exactly its data.
5. **Never empty the near-nominal region**: q is at most ``MAX_DISTANCE_EXPONENT`` (3). Half the radius holds
   P(d <= 0.5) = 0.5^q of the vectors: 12.5 % at q = 3, 0.2 % at the q = 9.2 the 270 V rudder actuator's
   pilot asked for (its faults leave it healthy further out). Real actuators live near nominal, and a store
   without them gave the rudder's FDI no near-nominal examples: on clean near-nominal records its
   eccentricity interval covered the truth 27 % of the time (docs/own_actuator.md). A target that needs more
   is not reached (``reached`` false, the expected fraction in the manifest), rather than reached at that cost.
6. **Keep a floor under the near-nominal density**: when the target needs q > 1, a share s
   (``dataset.near_nominal_share``) of the radial law stays the paper's, P(d <= a) = s a + (1 - s) a^q
   (``sampling.py``), and q is solved for the target under that law. Even at q's bound the store then holds
   s times the paper's density near nominal (within a tenth of the radius: 2.6 % of the vectors at s = 0.25, q = 3,
   against 0.1 % at s = 0), where a user's new actuators are read and tracked. The fraction reached moves
   towards the paper's by up to s times the gap. When q <= 1 the law is already denser there: s is not applied.

The calibration depends only on the config and the seed (the pilot's stream), so every shard, resume
and merge computes the same q; it is also cached in ``data_dir/sampling.json`` under the store's
fingerprint, so only the first run pays the pilot.
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from .generation import seed_streams
from .labels import LabelComputer
from .sampling import ImportanceSampler, radial_cdf
from .store import read_json, write_json

CALIBRATION_FILE = "sampling.json"
log = logging.getLogger(__name__)
MAX_DISTANCE_EXPONENT = 3.0  # the largest q: 12.5 % of the vectors within half the radius (step 5 above)


def isotonic_decreasing(y: np.ndarray) -> np.ndarray:
    """Least-squares non-increasing fit of y (n,) in the given order (pool adjacent violators)."""
    means: list[float] = []
    sizes: list[int] = []
    for v in np.asarray(y, dtype=np.float64):
        means.append(float(v))
        sizes.append(1)
        while len(means) > 1 and means[-2] < means[-1]:  # violates "non-increasing": pool the two
            m, n = means.pop(), sizes.pop()
            means[-1] = (means[-1] * sizes[-1] + m * n) / (sizes[-1] + n)
            sizes[-1] += n
    return np.repeat(means, sizes)


@dataclass
class ExponentCalibrator:
    """Chooses the distance exponent q of the importance sampler for a target healthy fraction.

    Args:
        target: the healthy fraction wanted, in (0, 1).
        tolerance: keep q = 1 (the paper) when the pilot's healthy fraction is within this of the target.
        exponent_bounds: (low, high) search interval of q.
        near_nominal_share: s in [0, 1), the paper's share of the radial law where q > 1 (step 6 above).

    Fitted attributes (``fit``): ``edges_`` (n + 1,) and ``health_`` (n,) the step function h(d) on
    [edges_i, edges_i+1) (d normalised by the radius), ``pilot_fraction_``, ``exponent_`` (q), ``share_`` (the
    share applied: s where q > 1, else 0), ``expected_fraction_`` (H(q) under that law), ``kept_paper_``,
    ``reached_`` (False: the target lies outside H(exponent_bounds), q is clamped to the nearer bound).
    """

    target: float
    tolerance: float = 0.05
    exponent_bounds: tuple[float, float] = (0.05, MAX_DISTANCE_EXPONENT)
    near_nominal_share: float = 0.0

    def __post_init__(self) -> None:
        t = self.target
        if isinstance(t, bool) or not isinstance(t, (int, float)) or not 0.0 < t < 1.0:
            raise ValueError(f"dataset.healthy_fraction must be in (0, 1) or null, got {t!r}")
        tol = self.tolerance
        if isinstance(tol, bool) or not isinstance(tol, (int, float)) or not 0.0 <= tol < 1.0:
            raise ValueError(f"dataset.healthy_fraction_tolerance must be in [0, 1), got {tol!r}")
        lo, hi = self.exponent_bounds
        if not 0 < lo < 1 < hi:
            raise ValueError(f"exponent_bounds must be (low, high) with 0 < low < 1 < high, got {self.exponent_bounds}")
        share = self.near_nominal_share
        if isinstance(share, bool) or not isinstance(share, (int, float)) or not 0.0 <= share < 1.0:
            raise ValueError(f"dataset.near_nominal_share must be in [0, 1), got {share!r}")

    def expected_fraction(self, q: float, share: float = 0.0) -> float:
        """H(q) of the fitted step function under the radial law with the paper's ``share`` [-]."""
        return float(np.sum(self.health_ * np.diff(radial_cdf(self.edges_, q, share))))

    def _solve(self, low: float, high: float, share: float) -> tuple[float, bool]:
        """(q, reached): H(q, share) = target by bisection on log q within [low, high], else the nearer bound."""
        lo, hi = math.log(low), math.log(high)
        if self.expected_fraction(low, share) < self.target:  # H non-increasing in q
            return low, False
        if self.expected_fraction(high, share) > self.target:
            return high, False
        for _ in range(60):
            mid = 0.5 * (lo + hi)
            lo, hi = (mid, hi) if self.expected_fraction(math.exp(mid), share) > self.target else (lo, mid)
        return math.exp(0.5 * (lo + hi)), True

    def fit(self, distance: np.ndarray, healthy: np.ndarray) -> ExponentCalibrator:
        """Fit on a pilot sampled with q = 1: ``distance`` (n,) d / r in [0, 1], ``healthy`` (n,) bool."""
        d = np.asarray(distance, dtype=np.float64)
        h = np.asarray(healthy, dtype=np.float64)
        if d.ndim != 1 or d.shape != h.shape or d.size < 2:
            raise ValueError(
                f"pilot: distance and healthy must be two (n,) arrays with n >= 2, got {d.shape} and {h.shape}"
            )
        order = np.argsort(d, kind="stable")
        d, h = d[order], h[order]
        self.health_ = isotonic_decreasing(h)
        self.edges_ = np.concatenate([[0.0], 0.5 * (d[1:] + d[:-1]), [1.0]]).clip(0.0, 1.0)
        self.pilot_fraction_ = float(h.mean())
        self.kept_paper_ = abs(self.pilot_fraction_ - self.target) <= self.tolerance
        self.reached_, self.share_ = True, 0.0
        if self.kept_paper_:
            self.exponent_ = 1.0
        else:
            low, high = self.exponent_bounds
            self.exponent_, self.reached_ = self._solve(low, high, 0.0)
            if self.exponent_ > 1.0 and self.near_nominal_share > 0.0:  # the samples move out: keep the floor
                self.share_ = float(self.near_nominal_share)
                self.exponent_, self.reached_ = self._solve(1.0 + 1e-9, high, self.share_)
            self.exponent_ = float(f"{self.exponent_:.4g}")
        self.expected_fraction_ = self.expected_fraction(self.exponent_, self.share_)
        return self


def calibrate(
    sampler: ImportanceSampler,
    assess: Callable[[np.ndarray], np.ndarray],
    target: float,
    tolerance: float,
    pilot_size: int,
    seed: np.random.SeedSequence,
    near_nominal_share: float = 0.0,
) -> dict[str, Any]:
    """Draw the pilot with ``sampler`` (its distance exponent must be 1), label it with ``assess``
    (K (n, 8) -> healthy (n,) bool) and fit the exponent (with the paper's ``near_nominal_share`` where q > 1).

    Returns:
        JSON-able record: ``healthy_fraction_target``, ``tolerance``, ``pilot_size``,
        ``pilot_healthy_fraction``, ``distance_exponent`` (q; the paper: 1), ``near_nominal_share`` (applied),
        ``expected_healthy_fraction``, ``kept_paper``, ``reached``.
    """
    if sampler.distance_exponent != 1.0:
        raise ValueError(f"the pilot uses the paper's scaling (distance_exponent 1), got {sampler.distance_exponent}")
    cal = ExponentCalibrator(target, tolerance, near_nominal_share=near_nominal_share)  # bad settings: before the pilot
    k = sampler.sample(pilot_size, seed)
    healthy = np.asarray(assess(k), dtype=bool)
    cal.fit(sampler.distance(k) / sampler.radius, healthy)
    return {
        "healthy_fraction_target": target,
        "tolerance": tolerance,
        "pilot_size": int(pilot_size),
        "pilot_healthy_fraction": round(cal.pilot_fraction_, 4),
        "distance_exponent": cal.exponent_,
        "near_nominal_share": cal.share_,
        "expected_healthy_fraction": round(cal.expected_fraction_, 4),
        "kept_paper": bool(cal.kept_paper_),
        "reached": bool(cal.reached_),
        "max_distance_exponent": cal.exponent_bounds[1],
    }


def paper_record() -> dict[str, Any]:
    """The record of an uncalibrated store (``dataset.healthy_fraction: null``): the paper's scaling."""
    return {"healthy_fraction_target": None, "distance_exponent": 1.0}


def load_or_calibrate(
    data_dir: Path, fingerprint: str, run: Callable[[], dict[str, Any]]
) -> tuple[dict[str, Any], float]:
    """The calibration cached in ``data_dir/sampling.json`` under ``fingerprint``, or ``run()``'s, cached.

    Returns:
        (the record, seconds spent on the pilot: 0 when cached).
    """
    path = Path(data_dir) / CALIBRATION_FILE
    if path.is_file():
        try:
            cached = read_json(path)
        except (OSError, ValueError):
            cached = {}
        if isinstance(cached, Mapping) and cached.get("fingerprint") == fingerprint and "calibration" in cached:
            return dict(cached["calibration"]), 0.0
    t0 = time.perf_counter()
    record = run()
    wall = time.perf_counter() - t0
    write_json(path, {"fingerprint": fingerprint, "calibration": record})
    return record, wall


def calibrate_spec(spec: Any, nominal: Any, assessment: Any, seed: int) -> dict[str, Any]:
    """The calibration of a ``DatasetSpec``: the paper's record when ``spec.healthy_fraction`` is null, else
    a pilot of ``spec.pilot_size`` vectors from the ``pilot`` seed stream, assessed in batches of
    ``spec.chunk_size`` when the sweep is compiled (the assessment batch of the signal chunks: it compiles once),
    else of up to ``spec.label_chunk_size`` (the labels split's batch). A label does not depend on its batch, so
    the batch only sets the cost: uncompiled, each simulated period costs the same Python overhead whatever the
    batch, and 64 vectors at a time took 7x longer per vector than 128 on a 20 kHz PWM actuator."""

    sampler = ImportanceSampler(tuple(nominal), spec.uniform, 1.0)
    if spec.healthy_fraction is None:
        return paper_record()
    sweep = getattr(assessment, "sweep", None)
    compiled = bool(getattr(sweep, "compile", False))
    batch = spec.chunk_size if compiled else min(max(spec.chunk_size, spec.label_chunk_size), spec.pilot_size)
    labeller = LabelComputer(assessment, nominal, batch)

    def assess(k: np.ndarray) -> np.ndarray:
        # the pilot is the first thing a new actuator's store computes, and on a slow loop it takes minutes:
        # say what it is doing, chunk by chunk
        healthy = []
        t0 = time.perf_counter()
        for i in range(0, len(k), batch):
            healthy.append(labeller(k[i : i + batch])["healthy"])
            done = min(i + batch, len(k))
            per_vector = (time.perf_counter() - t0) / done
            log.info(
                "importance sampling: healthy-fraction pilot, %d of %d vectors assessed, %.3f s a vector, "
                "~%.0f min left (cached afterwards; the store's labels cost the same per vector)",
                done,
                len(k),
                per_vector,
                per_vector * (len(k) - done) / 60,
            )
        return np.concatenate(healthy).astype(bool)

    return calibrate(
        sampler,
        assess,
        float(spec.healthy_fraction),
        float(spec.healthy_fraction_tolerance),
        spec.pilot_size,
        seed_streams(seed)["pilot"],
        float(spec.near_nominal_share),
    )
