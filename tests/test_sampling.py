"""Importance sampling (scaled Latin hypercube): the L-infinity distance from nominal is uniform."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.stats import kstest

from phm_torch.data.calibration import (
    MAX_DISTANCE_EXPONENT,
    ExponentCalibrator,
    calibrate,
    isotonic_decreasing,
)
from phm_torch.data.sampling import ImportanceSampler, radial_cdf, radial_quantile

NOMINAL = (0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.5, 0.5)


@pytest.fixture(scope="module")
def paper() -> ImportanceSampler:
    return ImportanceSampler(NOMINAL, (6,), 1.0)


def test_distance_from_nominal_is_uniform(paper):
    k = paper.sample(4000, 0)
    assert k.shape == (4000, 8) and k.dtype == np.float64
    assert ((k >= 0) & (k <= 1)).all()
    assert paper.n_rescaled == 7
    assert kstest(paper.distance(k), "uniform").pvalue > 0.01


def test_the_ks_test_detects_a_wrong_exponent(paper):
    # Without the rescaling, or with the exponent of all 8 parameters, the distance is not uniform.
    j = np.random.default_rng(0).random((4000, 8))
    assert kstest(paper.distance(j), "uniform").pvalue < 1e-6
    wrong = NOMINAL[:6] + (0.5,) + NOMINAL[7:]
    j8 = np.random.default_rng(1).random((4000, 8))
    k = j8.copy()
    k[:, :6] = j8[:, :6] ** 8
    u = np.abs(2 * j8[:, 7] - 1) ** 8
    k[:, 7] = np.where(j8[:, 7] >= 0.5, 0.5 + 0.5 * u, 0.5 - 0.5 * u)
    assert kstest(ImportanceSampler(wrong, (6,), 1.0).distance(k), "uniform").pvalue < 1e-3


def test_phase_uniform_and_gain_drift_symmetric(paper):
    k = paper.sample(4000, 1)
    assert kstest(k[:, 6], "uniform").pvalue > 0.01  # k7 not rescaled
    above = (k[:, 7] > 0.5).mean()
    assert 0.45 < above < 0.55  # k8 symmetric about its nominal 0.5
    assert kstest(np.abs(k[:, 7] - 0.5) / 0.5, lambda a: np.clip(a, 0, 1) ** (1 / 7)).pvalue > 0.01
    # denser near nominal: half of the damages below 0.5 ** 7
    assert abs(np.median(k[:, 0]) - 0.5**7) < 0.003


def test_latin_hypercube_strata(paper):
    # Every parameter's J has exactly one point per stratum of width 1/n.
    n = 256
    k = paper.sample(n, 2)
    j0 = k[:, 0] ** (1 / 7)
    assert sorted(np.floor(j0 * n).astype(int).tolist()) == list(range(n))


def test_restricted_domain_and_determinism():
    near = ImportanceSampler(NOMINAL, (6,), 0.1)
    k = near.sample(2000, 3)
    d = near.distance(k)
    assert d.max() <= 0.1 + 1e-12
    assert kstest(d / 0.1, "uniform").pvalue > 0.01
    assert np.array_equal(k, near.sample(2000, 3))
    assert not np.array_equal(k, near.sample(2000, 4))


@pytest.mark.parametrize(
    "kwargs, field",
    [
        ({"radius": 0.0}, "sampling.radius"),
        ({"radius": 1.5}, "sampling.radius"),
        ({"uniform": (9,)}, "sampling.uniform"),
        ({"nominal": (0.0,) * 7}, "sampling.nominal"),
    ],
)
def test_bad_sampler_config(kwargs, field):
    args = {"nominal": NOMINAL, "uniform": (6,), "radius": 1.0, **kwargs}
    with pytest.raises(ValueError, match=field):
        ImportanceSampler(**args)


# -- the distance exponent q and its calibration to a healthy fraction (phm_torch/data/calibration.py) ---------


@pytest.mark.parametrize("q", [0.5, 2.5])
def test_distance_exponent(q):
    # P(d <= a) = a ** q: d ** q is uniform; q = 1 is the paper's scaling, bit for bit
    s = ImportanceSampler(NOMINAL, (6,), 1.0, q)
    k = s.sample(4000, 5)
    assert ((k >= 0) & (k <= 1)).all()
    assert kstest(s.distance(k) ** q, "uniform").pvalue > 0.01
    # radial: the direction of the deviation is the paper's (same J): the normalised deviations keep their ratios
    paper = ImportanceSampler(NOMINAL, (6,), 1.0).sample(4000, 5)
    ratio = (k[:, :6] - 0.0) / np.maximum(paper[:, :6], 1e-300)
    assert np.allclose(ratio, (s.distance(k) / ImportanceSampler(NOMINAL, (6,), 1.0).distance(paper))[:, None])
    assert np.array_equal(k[:, 6], paper[:, 6])  # k7 untouched
    assert np.array_equal(
        ImportanceSampler(NOMINAL, (6,), 1.0, 1.0).sample(500, 6), ImportanceSampler(NOMINAL, (6,), 1.0).sample(500, 6)
    )


@pytest.mark.parametrize("target", [0.25, 0.3, 0.4])
def test_calibrated_exponent_on_a_synthetic_health_function(target):
    # healthy <=> d <= c: the healthy fraction at exponent q is c ** q, so q* = ln(target) / ln(c)
    c = 0.6
    sampler = ImportanceSampler(NOMINAL, (6,), 1.0)

    def assess(k):
        return sampler.distance(k) <= c

    rec = calibrate(sampler, assess, target, 0.02, 2000, np.random.SeedSequence(1))
    assert not rec["kept_paper"] and rec["reached"]
    assert rec["pilot_healthy_fraction"] == pytest.approx(c, abs=0.01)  # Latin hypercube: d uniform
    assert rec["distance_exponent"] == pytest.approx(math.log(target) / math.log(c), rel=0.03)
    calibrated = ImportanceSampler(NOMINAL, (6,), 1.0, rec["distance_exponent"])
    assert assess(calibrated.sample(4000, 2)).mean() == pytest.approx(target, abs=0.02)


def test_calibration_keeps_the_paper_within_tolerance():
    # a smooth health function already at the target: q stays exactly 1 (the store keeps its data)
    sampler = ImportanceSampler(NOMINAL, (6,), 1.0)
    rec = calibrate(sampler, lambda k: sampler.distance(k) <= 0.32, 0.3, 0.05, 1000, np.random.SeedSequence(3))
    assert rec["kept_paper"] and rec["distance_exponent"] == 1.0
    # an unreachable target (nothing healthy beyond d = 1e-4): clamped to the bound, reported
    rec = calibrate(sampler, lambda k: sampler.distance(k) <= 1e-4, 0.3, 0.05, 500, np.random.SeedSequence(3))
    assert not rec["reached"] and rec["distance_exponent"] == pytest.approx(0.05)


def test_the_exponent_never_empties_the_near_nominal_region():
    # healthy <=> d <= 0.6 and a target of 0.15 would need q = ln 0.15 / ln 0.6 = 3.7: capped at 3, which keeps
    # 0.5^3 = 12.5 % of the vectors within half the radius; reported as not reached, with the fraction it gives
    sampler = ImportanceSampler(NOMINAL, (6,), 1.0)
    rec = calibrate(sampler, lambda k: sampler.distance(k) <= 0.6, 0.15, 0.02, 2000, np.random.SeedSequence(1))
    assert not rec["reached"] and rec["distance_exponent"] == MAX_DISTANCE_EXPONENT == rec["max_distance_exponent"]
    assert rec["expected_healthy_fraction"] == pytest.approx(0.6**3, abs=0.02)
    capped = ImportanceSampler(NOMINAL, (6,), 1.0, rec["distance_exponent"])
    assert (capped.distance(capped.sample(4000, 2)) <= 0.5).mean() == pytest.approx(0.125, abs=0.02)


def test_isotonic_fit():
    y = np.array([1, 0, 1, 1, 0, 0, 1, 0], dtype=float)
    fit = isotonic_decreasing(y)
    assert np.all(np.diff(fit) <= 1e-12) and fit.mean() == pytest.approx(y.mean())
    assert fit.tolist() == pytest.approx([1, 2 / 3, 2 / 3, 2 / 3, 1 / 3, 1 / 3, 1 / 3, 0])


def test_calibration_on_a_real_pilot(params):
    # the reference actuator's assessment (a coarse auto sweep, 4 points per decade, for speed) pilot of 192
    # vectors, target 0.5 (the paper's scaling gives ~0.3): a fresh sample at the calibrated q is 0.5 +- 0.1
    import torch

    from phm_torch.assessment import AssessmentFunction, HealthRequirements, SineSweep, SweepDesign

    torch.set_num_threads(1)
    sweep = SineSweep("auto", "auto", 3, 2, 0.02, 1, 4, False, SweepDesign(points_per_decade=4))
    af = AssessmentFunction(params, sweep, HealthRequirements(45.0, 6.0, 0.9))
    sampler = ImportanceSampler(params.nominal_faults, (6,), 1.0)

    def assess(k):
        return af(torch.as_tensor(k)).healthy.numpy()

    rec = calibrate(sampler, assess, 0.5, 0.05, 192, np.random.SeedSequence(4))
    assert not rec["kept_paper"] and rec["distance_exponent"] < 1.0
    fresh = ImportanceSampler(params.nominal_faults, (6,), 1.0, rec["distance_exponent"]).sample(192, 5)
    assert assess(fresh).mean() == pytest.approx(0.5, abs=0.1)


@pytest.mark.parametrize(
    "kwargs, field",
    [
        ({"target": 0.0}, "dataset.healthy_fraction"),
        ({"target": 1.2}, "dataset.healthy_fraction"),
        ({"target": 0.3, "tolerance": -0.1}, "dataset.healthy_fraction_tolerance"),
    ],
)
def test_bad_calibration_config(kwargs, field):
    with pytest.raises(ValueError, match=field):
        ExponentCalibrator(**kwargs)
    with pytest.raises(ValueError, match="sampling.distance_exponent"):
        ImportanceSampler(NOMINAL, (6,), 1.0, 0.0)


# -- the floor under the near-nominal density (near_nominal_share) ------------------------------------------------


@pytest.mark.parametrize("q, share", [(3.0, 0.25), (2.0, 0.5)])
def test_near_nominal_share_is_the_mixture_law(q, share):
    # P(d <= a) = s a + (1 - s) a^q, reached radially: the directions and k7 are the paper's
    s = ImportanceSampler(NOMINAL, (6,), 1.0, q, share)
    k = s.sample(6000, 5)
    d = s.distance(k)
    for a in (0.05, 0.1, 0.3, 0.5, 0.8):
        assert (d <= a).mean() == pytest.approx(share * a + (1 - share) * a**q, abs=0.015)
    paper = ImportanceSampler(NOMINAL, (6,), 1.0).sample(6000, 5)
    ratio = k[:, :6] / np.maximum(paper[:, :6], 1e-300)
    assert np.allclose(ratio, (d / ImportanceSampler(NOMINAL, (6,), 1.0).distance(paper))[:, None])
    assert np.array_equal(k[:, 6], paper[:, 6])
    # the quantile inverts the law
    u = np.linspace(0.0, 1.0, 101)
    assert np.allclose(radial_cdf(radial_quantile(u, q, share), q, share), u, atol=1e-12)
    # share 0 is the plain exponent, bit for bit
    assert np.array_equal(
        ImportanceSampler(NOMINAL, (6,), 1.0, q, 0.0).sample(300, 6),
        ImportanceSampler(NOMINAL, (6,), 1.0, q).sample(300, 6),
    )


def test_calibration_keeps_a_floor_near_nominal_when_it_moves_samples_out():
    # healthy <=> d <= 0.7: a target of 0.3 needs q = ln 0.3 / ln 0.7 = 3.4 alone (capped at 3: 0.343). With a share
    # of 0.25 at the paper's scaling the law at q = 3 gives 0.25 * 0.7 + 0.75 * 0.343 = 0.432: not reached, said so,
    # and the near-nominal region holds a quarter of the paper's density
    sampler = ImportanceSampler(NOMINAL, (6,), 1.0)

    def assess(k):
        return sampler.distance(k) <= 0.7

    rec = calibrate(sampler, assess, 0.3, 0.02, 2000, np.random.SeedSequence(1), near_nominal_share=0.25)
    assert rec["near_nominal_share"] == 0.25 and not rec["reached"]
    assert rec["distance_exponent"] == MAX_DISTANCE_EXPONENT
    assert rec["expected_healthy_fraction"] == pytest.approx(0.25 * 0.7 + 0.75 * 0.7**3, abs=0.02)
    drawn = ImportanceSampler.from_record(rec, NOMINAL, (6,))
    k = drawn.sample(4000, 2)
    assert assess(k).mean() == pytest.approx(rec["expected_healthy_fraction"], abs=0.02)
    assert (drawn.distance(k) <= 0.1).mean() == pytest.approx(0.25 * 0.1 + 0.75 * 0.1**3, abs=0.008)

    # a reachable target under the mixture: q solved for it (healthy <=> d <= 0.6, target 0.35: q = 2.62)
    def healthy_within(c: float, target: float) -> dict:
        """The calibration with the floor of a health function healthy <=> d <= c."""
        return calibrate(
            sampler,
            lambda k: sampler.distance(k) <= c,
            target,
            0.02,
            2000,
            np.random.SeedSequence(1),
            near_nominal_share=0.25,
        )

    rec = healthy_within(0.6, 0.35)
    assert rec["reached"] and 1.0 < rec["distance_exponent"] < MAX_DISTANCE_EXPONENT
    assert 0.25 * 0.6 + 0.75 * 0.6 ** rec["distance_exponent"] == pytest.approx(0.35, abs=0.01)
    # the samples move towards nominal (q < 1): the law is denser there already, no share applied
    rec = healthy_within(0.2, 0.3)
    assert rec["distance_exponent"] < 1.0 and rec["near_nominal_share"] == 0.0
    # a record from before the share reads as none
    assert ImportanceSampler.from_record({"distance_exponent": 2.0}, NOMINAL, (6,)).near_nominal_share == 0.0
    with pytest.raises(ValueError, match="near_nominal_share"):
        ExponentCalibrator(0.3, near_nominal_share=1.0)
    with pytest.raises(ValueError, match="near_nominal_share"):
        ImportanceSampler(NOMINAL, (6,), 1.0, 2.0, -0.1)
