"""Platt scaling of the health verdict: recovers a known logistic law, refuses what it cannot fit."""

from __future__ import annotations

import pytest
import torch

from phm_torch.online.verdict import calibrate_verdict, verdict_quality


def test_recovers_a_known_logistic_law():
    g = torch.Generator().manual_seed(0)
    score = 0.3 + 0.5 * torch.randn(40000, generator=g, dtype=torch.float64)
    truth_a, truth_b = -6.0, 1.5
    faulty = torch.rand(40000, generator=g, dtype=torch.float64) < torch.sigmoid(truth_a * score + truth_b)
    a, b = calibrate_verdict(score, faulty, ridge=0.0)
    assert a == pytest.approx(truth_a, rel=0.05) and b == pytest.approx(truth_b, rel=0.08)
    p = torch.sigmoid(a * score + b)
    q = verdict_quality(p, faulty)
    assert q["brier"] < q["brier_base_rate"]                    # it knows more than the base rate
    assert 0.5 < q["accuracy"] <= 1.0


def test_separable_records_give_a_steep_but_finite_law():
    score = torch.linspace(-1, 1, 200, dtype=torch.float64)
    a, b = calibrate_verdict(score, score < 0)
    assert a < -5 and abs(b) < 1e-6 * abs(a) + 1e-6            # the boundary stays at score 0
    assert float(torch.sigmoid(torch.tensor(a * 0.5 + b))) < 0.1


def test_bad_input_is_named():
    score = torch.tensor([0.1, -0.2, 0.3], dtype=torch.float64)
    with pytest.raises(ValueError, match="needs healthy and faulty records, got 0 faulty of 3"):
        calibrate_verdict(score, torch.zeros(3, dtype=torch.bool))
    with pytest.raises(ValueError, match="score and faulty must both be"):
        calibrate_verdict(score, torch.zeros(2, dtype=torch.bool))
    with pytest.raises(ValueError, match="score must be finite"):
        calibrate_verdict(torch.tensor([0.1, float("nan")]), torch.tensor([True, False]))
