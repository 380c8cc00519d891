"""Damage propagation and RUL: torchdiffeq against the exact propagators, analytic crossings, bounds."""

from __future__ import annotations

import math

import pytest
import torch
from omegaconf import OmegaConf

from phm_torch.params import CONF_DIR, load_actuator
from phm_torch.prognostics import DamageModel, DeterministicRUL, RULEstimator

LAM = 5e-4  # 1/h
NOMINAL = list(load_actuator().nominal_faults)


def diagonal_model(noise: float = 0.0, **kw) -> DamageModel:
    f = torch.diag(torch.tensor([LAM] * 6 + [0.0, LAM], dtype=torch.float64))
    sd = [noise] * 6 + [0.0, noise]
    args = {"noise_correlation_hours": 100.0, "horizon_hours": 20000.0, "step_hours": 50.0, "nominal": NOMINAL} | kw
    return DamageModel(f.tolist(), sd, **args)


def threshold_score(k: torch.Tensor, thr: float = 0.3) -> torch.Tensor:
    return thr - k[:, :6].amax(1)


def shipped_model() -> DamageModel:
    cfg = OmegaConf.to_container(OmegaConf.load(CONF_DIR / "damage" / "coupled.yaml"))
    cfg.pop("_target_")
    return DamageModel(**cfg, nominal=NOMINAL)


def test_torchdiffeq_matches_exact_propagators():
    d = shipped_model()
    k0 = torch.tensor([[0.05, 0.02, 0.01, 0.0, 0.03, 0.04, 0.3, 0.6], [0.0] * 6 + [0.5, 0.5]], dtype=torch.float64)
    eps = torch.full((2, 200, 8), 1e-5, dtype=torch.float64)
    eps[:, :, 6] = 0
    traj = d.integrate(k0, eps)  # (T, B, 8)
    a, b = d.transitions(d.grid)
    exact = d.nominal + (a @ (k0 - d.nominal).T).permute(0, 2, 1) + (b @ eps[:, 0].T).permute(0, 2, 1)
    torch.testing.assert_close(traj, exact, rtol=1e-6, atol=1e-9)  # RK4 truncation at F h ~ 0.03
    assert torch.equal(traj[:, :, 6], k0[:, 6].expand_as(traj[:, :, 6]))  # k7 never grows


def test_rul_matches_analytic_crossing_per_sample():
    est = RULEstimator(diagonal_model(), threshold_score, refine_iterations=14)
    dk = torch.tensor([0.01, 0.05, 0.2, 1e-5], dtype=torch.float64)
    k0 = torch.zeros(4, 8, dtype=torch.float64)
    k0[:, 6] = k0[:, 7] = 0.5
    k0[torch.arange(4), torch.tensor([0, 2, 4, 1])] = dk
    rul, censored = est.first_crossing(k0)
    expected = torch.log(0.3 / dk) / LAM
    expected = torch.where(expected < 20000, expected, torch.full_like(expected, 20000.0))
    torch.testing.assert_close(rul, expected, rtol=0, atol=0.05)
    assert censored.tolist() == [False, False, False, True]


def test_already_faulty_and_never_faulty():
    est = RULEstimator(diagonal_model(), threshold_score)
    k0 = torch.tensor([[0.5] + [0.0] * 5 + [0.5, 0.5], [0.0] * 6 + [0.5, 0.5]], dtype=torch.float64)
    rul, censored = est.first_crossing(k0)
    assert rul[0] == 0 and not censored[0]
    assert rul[1] == 20000 and censored[1]


def test_monte_carlo_bounds_are_ordered_and_shrink_without_noise():
    k0 = torch.tensor([[0.02, 0.0, 0.0, 0.0, 0.0, 0.0, 0.5, 0.5]], dtype=torch.float64)
    noisy = RULEstimator(diagonal_model(noise=2e-6), threshold_score, n_samples=300)
    r = noisy.estimate(k0, torch.Generator().manual_seed(0))
    assert (r.empirical[0, 0] < r.empirical[0, 1] < r.empirical[0, 2]).item()
    assert (r.gaussian[0, 0] < r.gaussian[0, 1] < r.gaussian[0, 2]).item()
    # noise on the rate advances failure on average less than it spreads it: median near the analytic one
    analytic = math.log(0.3 / 0.02) / LAM
    assert r.empirical[0, 1].item() == pytest.approx(analytic, rel=0.1)
    quiet = RULEstimator(diagonal_model(noise=0.0), threshold_score, n_samples=20).estimate(k0)
    assert (quiet.empirical[0, 2] - quiet.empirical[0, 0]).item() < 1.0


def calibration_case() -> tuple[RULEstimator, torch.Tensor]:
    """A noisy diagonal model and 12 near-nominal vectors to calibrate the deterministic bands on."""
    est = RULEstimator(diagonal_model(noise=2e-6), threshold_score, n_samples=200)
    g = torch.Generator().manual_seed(1)
    k = torch.zeros(12, 8, dtype=torch.float64)
    k[:, 6:] = 0.5
    k[:, :6] = torch.rand(12, 6, generator=g, dtype=torch.float64) ** 4 * 0.1
    return est, k


def test_deterministic_variant_reproduces_monte_carlo_quantiles():
    est, k = calibration_case()
    det = DeterministicRUL(est)
    deltas = det.calibrate(k, torch.Generator().manual_seed(2))
    assert deltas[0] > deltas[1] > deltas[2]  # 5 % RUL needs the most damage
    pred = det.predict(k)
    mc = est.estimate(k, torch.Generator().manual_seed(3)).empirical
    ratio = (pred / mc).median(0).values
    torch.testing.assert_close(ratio, torch.ones(3, dtype=torch.float64), rtol=0, atol=0.15)


@pytest.mark.parametrize(
    "field,kwargs,match",
    [
        ("rate", {"rate": [[0.0] * 8] * 7}, "damage.rate must be a finite 8x8"),
        ("noise_std", {"noise_std": [-1.0] + [0.0] * 7}, "damage.noise_std"),
        ("step_hours", {"step_hours": 0.0}, "damage.step_hours must be > 0"),
    ],
)
def test_bad_damage_config(field, kwargs, match):
    base = {
        "rate": [[0.0] * 8] * 8,
        "noise_std": [0.0] * 8,
        "noise_correlation_hours": 100.0,
        "horizon_hours": 1000.0,
        "step_hours": 10.0,
        "nominal": NOMINAL,
    }
    with pytest.raises(ValueError, match=match):
        DamageModel(**(base | kwargs))
    rate = [[0.0] * 8 for _ in range(8)]
    rate[6][0] = 1e-4
    with pytest.raises(ValueError, match="column 7"):
        DamageModel(**(base | {"rate": rate}))


def test_coarse_event_search_equals_scoring_every_grid_point():
    """Scoring every 8th grid point and then the first faulty interval finds the same crossings as scoring
    every point, with noise, at the edges (already faulty, never faulty) and ~8x fewer score calls."""
    calls = {"fine": 0, "coarse": 0}

    def counted(name):
        def score(k):
            calls[name] += k.shape[0]
            return threshold_score(k, 0.25)

        return score

    d = diagonal_model(noise=3e-6)
    g = torch.Generator().manual_seed(3)
    k0 = torch.rand(300, 8, generator=g, dtype=torch.float64) * 0.05
    k0[:, 6] = 0.5
    k0[0, 0], k0[1] = 0.4, torch.tensor([0.0] * 6 + [0.5, 0.5])  # already faulty; slowest
    eps = d.sample_noise(300, g)
    fine = RULEstimator(d, counted("fine"), coarse=1).first_crossing(k0, eps)
    coarse = RULEstimator(d, counted("coarse"), coarse=8).first_crossing(k0, eps)
    torch.testing.assert_close(coarse[0], fine[0], rtol=0, atol=1e-9)
    assert torch.equal(coarse[1], fine[1])
    assert fine[0][0] == 0 and 0 < coarse[0][5] < 20000
    assert calls["coarse"] < calls["fine"] / 4
    with pytest.raises(ValueError, match="rul.coarse"):
        RULEstimator(d, threshold_score, coarse=0)


def test_removing_damage_stops_at_nominal_and_keeps_the_band_ordered():
    """A k8 just above nominal must not be pushed past it by a negative delta: it would then drift the
    other way and fail sooner, so the 95 % RUL would fall below the median."""

    def two_sided(k):
        return 0.3 - torch.maximum(k[:, :6].amax(1), 4.0 * (k[:, 7] - 0.5).abs())

    est = RULEstimator(diagonal_model(noise=1e-6), two_sided, refine_iterations=10)
    det = DeterministicRUL(est)
    k0 = torch.tensor([[0.02, 0.0, 0.0, 0.0, 0.0, 0.0, 0.5, 0.501]], dtype=torch.float64)
    less = det.disturbed(k0, -0.01)
    assert less[0, 7] == 0.5 and (less[0, :6] >= 0).all() and less[0, 0] == pytest.approx(0.01)
    more = det.disturbed(k0, 0.01)
    assert more[0, 7] == pytest.approx(0.511) and more[0, 0] == pytest.approx(0.03)
    r_less, r_mid, r_more = (det.rul(k0, d) for d in (-0.01, 0.0, 0.01))
    assert (r_less > r_mid).all() and (r_mid > r_more).all()
    below = k0.clone()
    below[0, 7] = 0.49  # the other side of nominal: symmetric
    assert det.disturbed(below, 0.01)[0, 7] == pytest.approx(0.48)


def test_bounds_are_the_extremes_of_the_three_propagations():
    from phm_torch.prognostics.rul import ordered_bounds

    rul = torch.tensor([[100.0, 200.0, 300.0], [250.0, 200.0, 150.0], [0.0, 50.0, 20.0]])
    assert ordered_bounds(rul).tolist() == [[100.0, 200.0, 300.0], [150.0, 200.0, 250.0], [0.0, 50.0, 50.0]]


def test_a_faster_wear_clock_divides_the_rul_exactly():
    """Without noise the damage ODE is linear in F: k(t; s F) = k(s t; F), so RUL(s F) = RUL(F) / s.
    The rate band rests on this; checked here with torchdiffeq on the shipped coupled model."""
    d = shipped_model()
    k0 = torch.tensor(
        [[0.02, 0.01, 0.0, 0.03, 0.0, 0.02, 0.5, 0.52], [0.04, 0.0, 0.0, 0.0, 0.0, 0.0, 0.5, 0.5]], dtype=torch.float64
    )

    def rul(model: DamageModel) -> torch.Tensor:
        return RULEstimator(model, threshold_score, refine_iterations=20, coarse=1).first_crossing(k0)[0]

    base = rul(d)
    for s in (0.8, 1.3):
        faster = DamageModel(
            (d.rate * s).tolist(), d.noise_std.tolist(), d.block, d.horizon, d.step, d.nominal.tolist()
        )
        torch.testing.assert_close(rul(faster), base / s, rtol=1e-3, atol=0.1)


def test_rate_band_reproduces_monte_carlo_quantiles_and_never_collapses():
    est, k = calibration_case()
    det = DeterministicRUL(est, "rate")
    det.calibrate(k, torch.Generator().manual_seed(2))
    assert det.scales_[0] > 1.0 == det.scales_[1] > det.scales_[2]  # 5 %: a faster clock
    pred = det.predict(k)
    torch.testing.assert_close(pred[:, 0], pred[:, 1] / det.scales_[0])
    assert (pred[:, 0] < pred[:, 1]).all() and (pred[:, 1] < pred[:, 2]).all()
    mc = est.estimate(k, torch.Generator().manual_seed(3)).empirical
    torch.testing.assert_close((pred / mc).median(0).values, torch.ones(3, dtype=torch.float64), rtol=0, atol=0.15)
    deltas, scales = det.pipeline_parameters()
    assert torch.equal(deltas, det.deltas_[1].repeat(3)) and torch.equal(scales, det.scales_)
    deltas, scales = det.pipeline_parameters("initial_state")
    assert torch.equal(deltas, det.deltas_) and torch.equal(scales, torch.ones(3, dtype=torch.float64))
    with pytest.raises(ValueError, match="rul.band"):
        DeterministicRUL(est, "time")
    with pytest.raises(ValueError, match="calibrate"):
        DeterministicRUL(est, "rate").predict(k)
