"""Importance sampling (scaled Latin hypercube): the L-infinity distance from nominal is uniform."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.stats import kstest

from phm_torch.data.sampling import ImportanceSampler

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
    assert kstest(k[:, 6], "uniform").pvalue > 0.01           # k7 not rescaled
    above = (k[:, 7] > 0.5).mean()
    assert 0.45 < above < 0.55                                 # k8 symmetric about its nominal 0.5
    assert kstest(np.abs(k[:, 7] - 0.5) / 0.5, lambda a: np.clip(a, 0, 1) ** (1 / 7)).pvalue > 0.01
    # denser near nominal: half of the damages below 0.5 ** 7
    assert abs(np.median(k[:, 0]) - 0.5 ** 7) < 0.003


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


@pytest.mark.parametrize("kwargs, field", [
    ({"radius": 0.0}, "sampling.radius"),
    ({"radius": 1.5}, "sampling.radius"),
    ({"uniform": (9,)}, "sampling.uniform"),
    ({"nominal": (0.0,) * 7}, "sampling.nominal"),
])
def test_bad_sampler_config(kwargs, field):
    args = {"nominal": NOMINAL, "uniform": (6,), "radius": 1.0, **kwargs}
    with pytest.raises(ValueError, match=field):
        ImportanceSampler(**args)
