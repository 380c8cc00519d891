"""How the reference RUL ends: a smooth crossing of phi_a's boundary, or a jump of its margin score.

The reference RUL stops each damage propagation where the assessment's margin score
(:func:`~.reference.margin_score`, the smallest relative excess over the requirements) turns negative. Where
that score falls smoothly through zero it grades the approach, and a health classifier's boundary error
costs hours in proportion to how fast the score moves. Where the score *jumps*, the binding reading switches
to another feature of the frequency response: the -3 dB bandwidth of a loop whose |T| sags to about -3 dB
below its resonance falls from beyond the resonance (~60 Hz on flap115) into the sag (~13 Hz) as the sag's
floor passes -3 dB, at a few hundredths of a dB per 10 h; or a margin becomes unmeasurable. The label there
changes with a quantity the score does not grade, the labels on either side differ by hundredths of a dB in
|T|, and the classifier's boundary, placed from such labels, errs by hundreds of hours.

Measured on flap115 (docs/results.md, "What flap115's RUL from the true k is made of"): 43 % of its rul
vectors end by a jump, where the RUL from the true k errs by a median 9.3 %, against 1.8 % on its smooth
crossings; the reference actuator's end by a jump on 1 of 171.

:func:`reference_crossings` reads the score just before and just after each reference crossing along the
median propagation (the same disturbed start and damage law as :func:`~.reference.reference_rul`);
:func:`crossing_metrics` splits the RUL-from-the-true-k error by the kind of crossing.
"""

from __future__ import annotations

import logging
from collections.abc import Callable

import torch

from .damage import DamageModel
from .evaluation import RULComparison
from .rul import DeterministicRUL, RULEstimator

log = logging.getLogger(__name__)

WINDOW_HOURS = 10.0  # the score is read this long before and after the crossing [h]
JUMP = 0.1  # a fall of the margin score by more than this across the window is a jump (relative excess)
JUMP_SHARE_WARNING = 0.2  # jumps at more than this share of the crossings: say what the RUL error is made of


def reference_crossings(
    damage: DamageModel,
    score: Callable[[torch.Tensor], torch.Tensor],
    k0: torch.Tensor,
    delta: float | torch.Tensor,
    reference: torch.Tensor,
    window_hours: float = WINDOW_HOURS,
) -> dict[str, torch.Tensor]:
    """The margin score just before and after each vector's reference crossing on its median propagation.

    Args:
        damage: the damage law of the reference.
        score: phi_a's margin score (B, 8) -> (B,), positive = healthy (:func:`~.reference.margin_score`).
        k0: (B, 8) the rul split's fault vectors.
        delta: the median propagation's disturbance (the calibrated ``deltas[1]``).
        reference: (B, 3) reference RUL 5/50/95 % [h].
        window_hours: how long before and after the median crossing the score is read [h] (> 0).

    Returns:
        ``inside`` (B,) bool: the median reference RUL lies strictly inside (0, horizon), a crossing to read;
        ``before``, ``after`` (B,) float64: the score at RUL - window and RUL + window (nan where not inside);
        ``window_hours`` (0-dim): the window.
    """
    if not window_hours > 0:
        raise ValueError(f"window_hours must be > 0, got {window_hours!r}")
    if k0.ndim != 2 or reference.shape != (k0.shape[0], 3):
        raise ValueError(f"k0 (B, 8) and reference (B, 3) expected, got {tuple(k0.shape)} and {tuple(reference.shape)}")
    det = DeterministicRUL(RULEstimator(damage, score, n_samples=2))
    t_cross = reference[:, 1].to(torch.float64)
    inside = (t_cross > 0) & (t_cross < damage.horizon)
    before = torch.full_like(t_cross, float("nan"))
    after = torch.full_like(t_cross, float("nan"))
    rows = inside.nonzero().flatten()
    if rows.numel():
        start = det.disturbed(k0[rows].to(torch.float64), delta)
        nominal = damage.nominal.to(start)
        times = torch.cat([(t_cross[rows] - window_hours).clamp(min=0.0), t_cross[rows] + window_hours])
        # exact propagator of the linear law without noise: k(t) = nominal + expm(F t) (k0 - nominal)
        a, _ = damage.transitions(times)
        dev = (start - nominal).repeat(2, 1)
        k = (nominal + torch.einsum("bij,bj->bi", a, dev)).clamp(0.0, 1.0)
        with torch.no_grad():
            s = score(k).to(torch.float64)
        n = rows.numel()
        before[rows], after[rows] = s[:n], s[n:]
    return {"inside": inside, "before": before, "after": after, "window_hours": torch.tensor(float(window_hours))}


def crossing_metrics(
    reference: torch.Tensor, true_k: torch.Tensor, crossings: dict[str, torch.Tensor], jump: float = JUMP
) -> dict[str, float | int]:
    """The RUL from the true k, split by how the reference crossing happens.

    Args:
        reference, true_k: (B, 3) RULs [h] (5/50/95 %).
        crossings: :func:`reference_crossings`'s result for the same vectors.
        jump: the score's fall across the window above which a crossing is a jump.

    Returns: ``rul_reference_crossings`` (vectors with a crossing inside the horizon),
    ``rul_reference_jump_crossings`` (of them, those whose score falls by more than ``jump``),
    ``rul_err_median_true_k_smooth`` / ``_jump`` (the median relative error on each; nan where none).
    """
    inside = crossings["inside"]
    is_jump = inside & ((crossings["before"] - crossings["after"]) > jump)
    smooth = inside & ~is_jump

    def err(rows: torch.Tensor) -> float:
        if not rows.any():
            return float("nan")
        return RULComparison(reference[rows], true_k[rows], true_k[rows]).metrics()["rul_err_median_true_k"]

    out: dict[str, float | int] = {
        "rul_reference_crossings": int(inside.sum()),
        "rul_reference_jump_crossings": int(is_jump.sum()),
        "rul_err_median_true_k_smooth": err(smooth),
        "rul_err_median_true_k_jump": err(is_jump),
    }
    n = out["rul_reference_crossings"]
    if n and out["rul_reference_jump_crossings"] > JUMP_SHARE_WARNING * n:
        log.warning(
            "the assessment's margin score jumps (by more than %.2f within %g h) at %d of %d reference crossings: "
            "there the binding reading switches to another feature of the response (e.g. a -3 dB bandwidth falling "
            "from beyond the resonance into a sag of |T| near -3 dB), a boundary the score does not grade and a "
            "classifier places only roughly; RUL from the true k: median error %.1f %% on the jumps, %.1f %% on the "
            "smooth crossings (docs/own_actuator.md §9, 'Is the RUL error from the true k the classifier's, or the "
            "assessment's?')",
            jump,
            float(crossings.get("window_hours", WINDOW_HOURS)),
            out["rul_reference_jump_crossings"],
            n,
            100 * out["rul_err_median_true_k_jump"],
            100 * out["rul_err_median_true_k_smooth"],
        )
    return out
