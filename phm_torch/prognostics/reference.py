"""Reference RUL: the damage propagation stopped by the true assessment function (the paper's "full model").

The assessment function costs one batch of LF frequency-response simulations per call, so the reference
uses a coarser event grid than the online estimator (its ``step_hours``) and refines each crossing by
bisection; every call assesses all trajectories of all vectors at one time point in one batch.
"""

from __future__ import annotations

from collections.abc import Callable

import torch

from .damage import DamageModel
from .rul import DeterministicRUL, RULEstimator, ordered_bounds


def margin_score(assess: Callable[[torch.Tensor], object]) -> Callable[[torch.Tensor], torch.Tensor]:
    """Health score from an assessment function: the smallest relative margin excess (B,).

    f(k) = min over requirements of (measured - required) / required, positive iff every requirement is
    met (the binary phi_a), negative when one fails; an unmeasurable margin (NaN) counts as failed.
    """

    def score(k: torch.Tensor) -> torch.Tensor:
        a = assess(k)
        req = assess.requirements
        m = a.margins
        bw_min = req.bandwidth_fraction * assess.nominal_bandwidth_hz
        parts = torch.stack(
            [
                (m.phase_margin_deg - req.phase_margin_deg) / req.phase_margin_deg,
                (m.gain_margin_db - req.gain_margin_db) / max(req.gain_margin_db, 1e-9),
                (m.bandwidth_hz - bw_min) / bw_min,
            ],
            dim=1,
        ).to(torch.float64)
        s = torch.nan_to_num(parts, nan=-1.0).amin(1)
        # keep the binary decision exact: the score's sign is phi_a's label
        return torch.where(a.healthy, s.clamp(min=1e-6), s.clamp(max=-1e-6))

    return score


def reference_rul(
    damage: DamageModel,
    score: Callable[[torch.Tensor], torch.Tensor],
    k0: torch.Tensor,
    deltas: torch.Tensor,
    step_hours: float = 500.0,
    refine_iterations: int = 8,
) -> torch.Tensor:
    """RUL 5/50/95 % [h] (B, 3) with the given (true) score, by the deterministic delta variant.

    Args:
        damage: the propagation model (its noise sets the disturbance direction).
        score: health score, positive = healthy (e.g. :func:`margin_score` of the assessment function).
        k0: (B, 8) initial fault vectors.   deltas: (3,) calibrated disturbances (see DeterministicRUL).
        step_hours: coarse event grid of the reference [h].
    """
    coarse = DamageModel(
        damage.rate.tolist(),
        damage.noise_std.tolist(),
        damage.block,
        damage.horizon,
        step_hours,
        damage.nominal.tolist(),
    )
    # coarse=1: the true score is evaluated at every point of its (already coarse) grid
    det = DeterministicRUL(RULEstimator(coarse, score, n_samples=2, refine_iterations=refine_iterations, coarse=1))
    det.deltas_ = torch.as_tensor(deltas, dtype=torch.float64)
    b = k0.shape[0]
    # one batch per grid call for the three disturbances together
    k = torch.cat([det.disturbed(k0, d) for d in det.deltas_])
    rul, _ = det.estimator.first_crossing(k)
    return ordered_bounds(rul.view(3, b).T)
