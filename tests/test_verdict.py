"""Platt scaling of the health verdict: recovers a known logistic law, refuses what it cannot fit."""

from __future__ import annotations

import pytest
import torch

from phm_torch.online.verdict import calibrate_verdict, shift_prior, verdict_quality


def test_recovers_a_known_logistic_law():
    g = torch.Generator().manual_seed(0)
    score = 0.3 + 0.5 * torch.randn(40000, generator=g, dtype=torch.float64)
    truth_a, truth_b = -6.0, 1.5
    faulty = torch.rand(40000, generator=g, dtype=torch.float64) < torch.sigmoid(truth_a * score + truth_b)
    a, b = calibrate_verdict(score, faulty, ridge=0.0)
    assert a == pytest.approx(truth_a, rel=0.05) and b == pytest.approx(truth_b, rel=0.08)
    p = torch.sigmoid(a * score + b)
    q = verdict_quality(p, faulty)
    assert q["brier"] < q["brier_base_rate"]  # it knows more than the base rate
    assert 0.5 < q["accuracy"] <= 1.0
    assert q["faulty_fraction"] == pytest.approx(float(faulty.double().mean()))
    # a split of healthy records only: the base rate's 0 is hindsight, not a reference
    one_class = verdict_quality(p[:100], torch.zeros(100, dtype=torch.bool))
    assert one_class["brier_base_rate"] is None and one_class["faulty_fraction"] == 0.0


def test_separable_records_give_a_steep_but_finite_law():
    score = torch.linspace(-1, 1, 200, dtype=torch.float64)
    a, b = calibrate_verdict(score, score < 0)
    assert a < -5 and abs(b) < 1e-6 * abs(a) + 1e-6  # the boundary stays at score 0
    assert float(torch.sigmoid(torch.tensor(a * 0.5 + b))) < 0.1


def test_bad_input_is_named():
    score = torch.tensor([0.1, -0.2, 0.3], dtype=torch.float64)
    with pytest.raises(ValueError, match="needs healthy and faulty records, got 0 faulty of 3"):
        calibrate_verdict(score, torch.zeros(3, dtype=torch.bool))
    with pytest.raises(ValueError, match="score and faulty must both be"):
        calibrate_verdict(score, torch.zeros(2, dtype=torch.bool))
    with pytest.raises(ValueError, match="score must be finite"):
        calibrate_verdict(torch.tensor([0.1, float("nan")]), torch.tensor([True, False]))


def test_prior_shift_transfers_the_law_to_another_fault_rate():
    """Scores drawn per class (healthy ~ N(1, 1), faulty ~ N(-1, 1)); calibrated where 70 % are faulty,
    shifted to 20 %, the law matches the one fitted directly on a 20 % population."""
    g = torch.Generator().manual_seed(1)

    def population(n: int, rate: float) -> tuple[torch.Tensor, torch.Tensor]:
        faulty = torch.rand(n, generator=g, dtype=torch.float64) < rate
        return torch.where(faulty, -1.0, 1.0) + torch.randn(n, generator=g, dtype=torch.float64), faulty

    a, b = calibrate_verdict(*population(60000, 0.7), ridge=0.0)
    a2, b2 = calibrate_verdict(*population(60000, 0.2), ridge=0.0)
    assert a == pytest.approx(a2, rel=0.05) and a == pytest.approx(-2.0, rel=0.05)  # log LR slope of the classes
    assert shift_prior(b, 0.7, 0.2) == pytest.approx(b2, abs=0.05)
    with pytest.raises(ValueError, match="prior must be in"):
        shift_prior(b, 0.7, 1.0)


@pytest.mark.parametrize(
    "value, message",
    [(1.0, r"verdict.prior_faulty must be in \(0, 1\), got 1.0"), (0, r"verdict.prior_faulty must be > 0, got 0")],
)
def test_evaluate_refuses_a_bad_prior_before_any_work(compose, tmp_path, value, message):
    from phm_torch.apps.evaluate import evaluate_rul

    with pytest.raises(ValueError, match=message):
        evaluate_rul(
            compose(
                "evaluate",
                [f"verdict.prior_faulty={value}", f"data_dir={tmp_path / 'none'}", f"out_dir={tmp_path / 'out'}"],
            )
        )
