"""Components the FDI does not identify (phm-evaluate's R^2 below 0.25): their k_hat is the training prior, not a
measurement of k, and the tracker must not fuse it. Checked on the small synthetic pipeline of test_tracking: the
Kalman update leaves an unread component alone, the law's prediction from new is its prior, and along a history
whose k_hat of one component is a constant prior mean the filter stays with the truth instead of converging on it."""

from __future__ import annotations

import math

import torch
from test_tracking import damage_config, filter_state, make_pipeline, scale_of, tracker, truth_path

from phm_torch.tracking import DamageLaw, kalman
from phm_torch.tracking.inspection import unread

PIPELINE = make_pipeline()
LAW = DamageLaw.from_config(damage_config(), PIPELINE, "test")


def test_an_unread_component_is_left_alone_and_weighs_nothing():
    m, c, k_hat, scale = filter_state(0, 0.3, 1e-5)
    observed = torch.ones(2, 8, dtype=torch.bool)
    observed[:, 5] = False
    observed[1, 2] = False
    m1, c1, ll1 = kalman.update(m, c, k_hat, scale, observed)
    # the same update with those readings infinitely uncertain
    huge = torch.where(observed, scale, torch.full_like(scale, 1e8))
    m2, c2, ll2 = kalman.update(m, c, k_hat, huge)
    torch.testing.assert_close(m1, m2, rtol=0, atol=1e-9)
    torch.testing.assert_close(c1, c2, rtol=0, atol=1e-12)
    # up to the constant -0.5 log(1e16) per unread component, the same log-likelihood
    torch.testing.assert_close(
        ll1 - ll2, ((~observed).sum(1, keepdim=True).double() * 0.5 * math.log(1e16)).expand_as(ll1), rtol=0, atol=1e-6
    )
    # all read: the update of old
    m3, c3, ll3 = kalman.update(m, c, k_hat, scale, torch.ones(2, 8, dtype=torch.bool))
    m4, c4, ll4 = kalman.update(m, c, k_hat, scale)
    torch.testing.assert_close((m3, c3, ll3), (m4, c4, ll4), rtol=0, atol=0)


def test_the_prior_from_new_is_the_laws_own_growth_of_its_noise():
    s = torch.tensor([[1.0, 2.0]], dtype=torch.float64)
    hours = torch.tensor([800.0], dtype=torch.float64)
    m, c = kalman.from_nominal(LAW, s, hours)
    torch.testing.assert_close(m, LAW.nominal.expand(1, 2, 8), rtol=0, atol=0)
    # the constant (the phase: no rate, no eps) is anywhere in [0, 1]
    assert float(c[0, 0, 6, 6]) == float(c[0, 1, 6, 6]) == kalman.CONSTANT_VARIANCE
    # a component the law grows (F_jj = 5e-4 / h) ends with more than the integral of its eps, the faster wearer more
    eps_var = float(LAW.noise_std_over(hours)[0, 0]) ** 2
    grown = [float(c[0, p, 0, 0]) for p in range(2)]
    assert eps_var < grown[0] < grown[1]
    # and by the growth of eps added uniformly over the interval: int_0^T exp(2 s f (T - t)) dt / T
    for p, rate in enumerate((1.0, 2.0)):
        x = 2.0 * rate * 5e-4 * 800.0
        assert abs(grown[p] / (eps_var * math.expm1(x) / x) - 1.0) < 0.02
    # new: nothing but the constant's spread; within new_spread of nominal, the uniform's mean and variance
    _, c0 = kalman.from_nominal(LAW, s, torch.zeros(1, dtype=torch.float64))
    assert float(c0[..., :6, :6].abs().max()) == 0.0
    m0, c0 = kalman.from_nominal(LAW, s, torch.zeros(1, dtype=torch.float64), 0.01)
    torch.testing.assert_close(m0[0, 0, :6], torch.full((6,), 0.005, dtype=torch.float64), rtol=0, atol=1e-15)
    torch.testing.assert_close(c0[0, 0, :6, :6].diagonal(), torch.full((6,), 1e-4 / 12, dtype=torch.float64))
    # gain drift, nominal 0.5 inside [0, 1]: either side, mean nominal
    assert float(m0[0, 0, 7]) == 0.5 and abs(float(c0[0, 0, 7, 7]) - 1e-4 / 3) < 1e-15


N_ACTUATORS, HELD = 40, 4  # histories; the component whose k_hat is the training prior


def run(held: bool, prior_mean: float = 0.4, n: int = 20) -> tuple[torch.Tensor, object]:
    """``N_ACTUATORS`` histories from new (each damage within the tracker's ``new_spread`` of nominal, as the life
    generator draws them) whose component ``HELD`` reads the training prior ``prior_mean`` (90 % interval: the whole
    range) at every inspection; (the true k at the last (A, 8), the last posterior)."""
    g = torch.Generator().manual_seed(3)
    start = torch.zeros(N_ACTUATORS, 8, dtype=torch.float64)
    start[:, :6] = 0.01 * torch.rand(N_ACTUATORS, 6, generator=g, dtype=torch.float64)
    start[:, 6:] = 0.5
    k = torch.stack([truth_path(LAW, row.tolist(), 1.0, n) for row in start], 1)  # (n, A, 8)
    names = [f"A{i:02d}" for i in range(N_ACTUATORS)]
    tr = tracker(PIPELINE, LAW, n_particles=128)
    scale = scale_of(k[0])
    scale[:, HELD] = 0.6 / 1.645
    observed = torch.ones(N_ACTUATORS, 8, dtype=torch.bool)
    observed[:, HELD] = False
    for i in range(n):
        k_hat = k[i].clone()
        k_hat[:, HELD] = prior_mean
        post = tr.update(
            names,
            torch.full((N_ACTUATORS,), 200.0 * i),
            k_hat,
            scale,
            torch.ones(N_ACTUATORS, dtype=torch.bool),
            observed=observed if held else None,
        )
    return k[-1], post


def test_a_prior_read_as_a_measurement_pulls_k_to_it_and_the_unread_one_follows_the_law():
    truth, fused = run(held=False)
    inside = (fused.k_low[:, HELD] <= truth[:, HELD]) & (truth[:, HELD] <= fused.k_high[:, HELD])
    # read as a measurement, the prior pulls k there (and the law grows it) with an interval that misses the truth
    assert float(fused.k_mean[:, HELD].min()) > 0.3 and not bool(inside.any())
    truth, held = run(held=True)
    inside = (held.k_low[:, HELD] <= truth[:, HELD]) & (truth[:, HELD] <= held.k_high[:, HELD])
    # not read: the law's prediction from new, whose 5-95 % interval holds the truth of 90 % of the histories
    assert float(inside.double().mean()) >= 0.85
    assert abs(float(held.k_mean[:, HELD].mean() - truth[:, HELD].mean())) < 0.01
    # the components it reads are tracked as before
    torch.testing.assert_close(held.k_mean[:, :4], fused.k_mean[:, :4], rtol=0, atol=0.01)


def test_the_near_nominal_readings_own_identification_decides_where_it_reads():
    pipeline_unread = ["eccentricity", "eccentricity_phase"]
    near = {"k_near_nominal": {"dry_friction": 0.0}, "k_near_nominal_not_identified": ["eccentricity_phase"]}
    assert unread(near, pipeline_unread) == ["eccentricity_phase"]
    # a near-nominal file calibrated before it measured R^2: the pipeline's list
    assert unread({**near, "k_near_nominal_not_identified": None}, pipeline_unread) == pipeline_unread
    # the pipeline's reading
    assert unread({"k_near_nominal": None, "k_near_nominal_not_identified": []}, pipeline_unread) == pipeline_unread
