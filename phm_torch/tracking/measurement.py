"""Measurement model: the pipeline's k_hat and its calibrated error.

phm-evaluate calibrates, per difficulty class and noise level, the half-width w of a 90 % interval of the true
k around k_hat (``OnlinePipeline.k_interval``). The tracker reads k_hat = k + e with e of scale w / t_0.95(dof)
(``dof = inf``, the default: the Gaussian whose central 90 % is +/- w), in the Kalman filters of :mod:`.kalman`.

The record's own verdict is a second reading, of the health now: its P(faulty) p was Platt-scaled by phm-evaluate
on held-out records whose fault rate was pi (the pipeline's ``verdict_prior_faulty``), so the record's likelihood
ratio P(record | faulty) / P(record | healthy) is the posterior odds over the prior odds,
(p / (1 - p)) / (pi / (1 - pi)) (:func:`verdict_odds`). The tracker weighs the RUL particles already faulty by it
(:class:`~.particle_rul.ParticleRUL`). The verdict is a function of the same record's k_hat, which the filter has
read: counting it again is an approximation, kept because the verdict classifier learned where the FDI's
estimates put the boundary (its errors there are not the Gaussian the filter assumes); measured in
docs/prognostics.md.
"""

from __future__ import annotations

import math

import torch
from scipy import stats

Z95 = 1.6448536269514722  # the standard normal's 95 % quantile
MIN_SCALE = 1e-4  # [k units]: a zero-width interval (a clamped bound) is not a perfect measurement


def t_quantile_95(dof: float) -> float:
    """The 95 % quantile of a Student-t with ``dof`` degrees of freedom (inf: the normal's)."""
    if not dof > 0:
        raise ValueError(f"measurement_dof must be > 0 (inf: Gaussian), got {dof!r}")
    return Z95 if math.isinf(dof) else float(stats.t.ppf(0.95, dof))


def interval_scale(k_hat: torch.Tensor, lower: torch.Tensor, upper: torch.Tensor, dof: float) -> torch.Tensor:
    """Error scale (B, 8) [k units] from the 90 % interval [lower, upper] (B, 8) around k_hat (B, 8).

    The interval is clamped to [0, 1], so the half-width is the larger of the two sides."""
    w = torch.maximum(upper - k_hat, k_hat - lower).to(torch.float64)
    return (w / t_quantile_95(dof)).clamp(min=MIN_SCALE)


# the reading the filter fused, as track.json records it, first found: the near-nominal FDI's, the pipeline's k_hat
# through the FDI response's inverse, the pipeline's k_hat; each (value key, 90 % interval key)
READINGS = (
    ("k_hat_near_nominal", "k_hat_near_nominal_interval"),
    ("k_hat_corrected", "k_hat_corrected_interval"),
    ("k_hat", "k_interval"),
)

ODDS_CLIP = 1e-6  # P(faulty) clipped to [this, 1 - this]: a record never decides alone


def verdict_odds(p_faulty: list[float | None], prior: float | None) -> torch.Tensor | None:
    """Likelihood ratios (B,) P(record | faulty) / P(record | healthy) of records with calibrated P(faulty)
    ``p_faulty`` (None: no verdict, ratio 1), Platt-scaled at the fault rate ``prior`` in (0, 1); None without a
    prior (the pipeline does not record it: no evidence)."""
    if prior is None:
        return None
    if not 0.0 < prior < 1.0:
        raise ValueError(f"verdict_prior_faulty must be in (0, 1), got {prior!r}")
    prior_odds = prior / (1.0 - prior)
    out = []
    for p in p_faulty:
        if p is None or not math.isfinite(p):
            out.append(1.0)
            continue
        q = min(max(float(p), ODDS_CLIP), 1.0 - ODDS_CLIP)
        out.append(q / (1.0 - q) / prior_odds)
    return torch.tensor(out, dtype=torch.float64)
