"""prognostics/crossings.py: a reference crossing read as smooth or as a jump of the margin score, and the RUL
from the true k split by it."""

from __future__ import annotations

import math

import pytest
import torch

from phm_torch.prognostics.crossings import crossing_metrics, reference_crossings
from phm_torch.prognostics.damage import DamageModel
from phm_torch.prognostics.reference import reference_rul

RATE = 1e-3  # [1/h]: dk1/dt = RATE k1, so k1(t) = k1(0) exp(RATE t)


def _damage() -> DamageModel:
    rate = [[0.0] * 8 for _ in range(8)]
    rate[0][0] = RATE
    return DamageModel(rate, [1e-6] + [0.0] * 7, 100.0, 20000.0, 50.0, [0, 0, 0, 0, 0, 0, 0.5, 0.5])


def _k(*k1: float) -> torch.Tensor:
    return torch.tensor([[v, 0, 0, 0, 0, 0, 0.5, 0.5] for v in k1], dtype=torch.float64)


def smooth(x: torch.Tensor) -> torch.Tensor:
    """Healthy while k1 < 0.6, the excess falling linearly in k1 (slope 1)."""
    return 0.6 - x[:, 0]


def knife_edge(x: torch.Tensor) -> torch.Tensor:
    """The same boundary, but the score falls from +0.02 to -0.4 there (a reading that jumps)."""
    return torch.where(x[:, 0] < 0.6, torch.full_like(x[:, 0], 0.02), torch.full_like(x[:, 0], -0.4))


def test_the_score_is_read_on_the_exact_median_propagation_either_side_of_the_crossing():
    """k1(t) = k1(0) exp(RATE t): either side of the crossing at ln(0.6 / k1) / RATE the smooth score is
    +-0.6 (exp(0.01) - 1) ~ +-6e-3 at +-10 h (within 15 %: the reference's RK4 on its 500 h grid places the crossing
    to about an hour, 6e-4 of score); the step reads +0.02 / -0.4."""
    damage, k = _damage(), _k(0.1, 0.3, 0.7)
    deltas = torch.zeros(3, dtype=torch.float64)
    ref = reference_rul(damage, smooth, k, deltas, 500.0, 12)
    assert ref[0, 1] == pytest.approx(math.log(6.0) / RATE, rel=1e-3) and ref[2, 1] == 0
    c = reference_crossings(damage, smooth, k, 0.0, ref)
    assert c["inside"].tolist() == [True, True, False]
    assert math.isnan(c["before"][2]) and math.isnan(c["after"][2])
    expected = 0.6 * (math.exp(RATE * 10.0) - 1.0)
    assert c["before"][:2].tolist() == pytest.approx([expected] * 2, rel=0.15)
    assert c["after"][:2].tolist() == pytest.approx([-expected] * 2, rel=0.15)
    jumps = reference_crossings(damage, knife_edge, k, 0.0, ref)
    assert jumps["before"][:2].tolist() == [0.02, 0.02] and jumps["after"][:2].tolist() == [-0.4, -0.4]
    with pytest.raises(ValueError, match="window_hours"):
        reference_crossings(damage, smooth, k, 0.0, ref, window_hours=0.0)


def test_the_rul_error_is_split_by_the_kind_of_crossing(caplog):
    """Two vectors cross smoothly and two by a jump; the true-k RULs err by 1 / 3 % and 10 / 20 %: the medians
    per kind (torch's median of two is the lower one) are 1 % and 10 %; a vector already faulty is no crossing."""
    damage = _damage()
    k = _k(0.1, 0.2, 0.3, 0.4, 0.7)
    deltas = torch.zeros(3, dtype=torch.float64)

    def mixed(x: torch.Tensor) -> torch.Tensor:  # the first two vectors' paths cross smoothly, the others jump
        return torch.where(x[:, 1] < 0.5, smooth(x), knife_edge(x))

    k[2:4, 1] = 0.9  # a marker the damage law leaves alone (column 2 has no rate): these two jump
    ref = reference_rul(damage, mixed, k, deltas, 500.0, 12)
    c = reference_crossings(damage, mixed, k, 0.0, ref)
    rel = torch.tensor([0.01, 0.03, 0.10, 0.20, 0.0], dtype=torch.float64)
    true_k = ref * (1 + rel).unsqueeze(1)
    with caplog.at_level("WARNING", logger="phm_torch.prognostics.crossings"):
        m = crossing_metrics(ref, true_k, c)
    assert "jumps (by more than 0.10 within 10 h) at 2 of 4 reference crossings" in caplog.text
    caplog.clear()
    assert m["rul_reference_crossings"] == 4 and m["rul_reference_jump_crossings"] == 2
    assert m["rul_err_median_true_k_smooth"] == pytest.approx(0.01, rel=1e-6)
    assert m["rul_err_median_true_k_jump"] == pytest.approx(0.10, rel=1e-6)
    with caplog.at_level("WARNING", logger="phm_torch.prognostics.crossings"):
        none = crossing_metrics(ref, true_k, reference_crossings(damage, smooth, k, 0.0, ref))
    assert caplog.text == ""  # no jump, no warning
    assert none["rul_reference_jump_crossings"] == 0 and math.isnan(none["rul_err_median_true_k_jump"])
