"""The gappy-residual OOD threshold that follows each record's noise (phm_torch/online/noise_threshold.py)."""

from __future__ import annotations

import pytest
import torch
from test_forward_check import N_E, N_LATENT, OracleFDI, _damage, faults, records

from phm_torch.online import OnlinePipeline
from phm_torch.online.noise_threshold import NoiseScaledThreshold, calibrate_gappy_residual, conformal_quantile
from phm_torch.surrogates import POD, GappyPOD, add_noise, rms
from phm_torch.surrogates.classifiers.polynomial_svm import PolynomialSVM

pytestmark = pytest.mark.torchscript  # scripts, saves or loads TorchScript on purpose


def test_threshold_interpolates_between_levels_and_holds_beyond():
    t = NoiseScaledThreshold([1.0, 3.0, 4.0], [0.01, 0.03, 0.1], dtype=torch.float64)
    got = t(torch.tensor([0.0, 0.01, 0.02, 0.03, 0.065, 0.1, 0.5], dtype=torch.float64))
    torch.testing.assert_close(got, torch.tensor([1.0, 1.0, 2.0, 3.0, 3.5, 4.0, 4.0], dtype=torch.float64))
    assert torch.equal(NoiseScaledThreshold(2.0)(torch.rand(5)), torch.full((5,), 2.0))
    for values, levels in (([1.0, 2.0], [0.03, 0.01]), ([1.0, 0.0], [0.01, 0.03]), ([1.0], [0.01, 0.03])):
        with pytest.raises(ValueError, match="noise-scaled threshold"):
            NoiseScaledThreshold(values, levels)


def test_conformal_quantile_is_the_ceil_rank():
    v = torch.arange(1.0, 101.0)
    assert conformal_quantile(v, 0.9) == 91.0  # ceil(101 * 0.9) = 91st smallest
    assert conformal_quantile(v, 0.999) == 100.0  # too few values for q: the largest
    assert conformal_quantile(torch.tensor([float("nan"), 2.0]), 0.5) == 2.0
    with pytest.raises(ValueError, match="no finite"):
        conformal_quantile(torch.tensor([float("nan")]), 0.5)


@pytest.fixture(scope="module")
def pipeline_and_data():
    torch.set_num_threads(1)
    k = faults(1200, 0)
    y = records(k)
    pod = POD(N_LATENT).fit(y)
    gappy = GappyPOD(pod.modes_, pod.mean_, torch.linspace(0, N_E - 1, 24).round().long())
    train = add_noise(y, rms(y), 0.01, torch.Generator().manual_seed(1))
    with torch.no_grad():
        floor = float(torch.quantile(gappy(gappy.select(train))[1].double(), 0.999))  # phm-train's threshold
    clf = PolynomialSVM(degree=2).fit(k[:300], k[:300, :5].amax(1) < 0.5)
    pipe = OnlinePipeline(
        gappy,
        OracleFDI(pod),
        clf,
        _damage(),
        torch.tensor([0.02, 0.0, -0.02]),
        torch.ones(8),
        N_E,
        residual_threshold=floor,
    ).eval()
    return pipe, floor


def _flagged(pipe, level: float, seed: int) -> float:
    clean = records(faults(400, seed))
    y = add_noise(clean, rms(clean), level, torch.Generator().manual_seed(seed)) if level else clean
    with torch.no_grad():
        return float(pipe(y)[3].double().mean())


def test_calibrated_threshold_passes_noisier_clean_records_and_still_flags_foreign_ones(pipeline_and_data):
    pipe, floor = pipeline_and_data
    before = _flagged(pipe, 0.03, 21)
    assert before > 0.5  # one threshold at 1 % noise rejects clean 3 % records
    cal = calibrate_gappy_residual(pipe, records(faults(500, 13)), [0.01, 0.03, 0.1], seed=0, quantile=0.995)
    values = cal["thresholds"]
    assert min(values) >= floor and values[0] < values[1] < values[2]  # grows with the noise, never below
    for level in (0.0, 0.01, 0.02, 0.03):
        assert _flagged(pipe, level, 22) <= 0.02, level
    clean = records(faults(50, 23))
    y = add_noise(clean, rms(clean), 0.01, torch.Generator().manual_seed(2))
    foreign = y + 0.3 * rms(y).unsqueeze(1) * torch.sin(torch.linspace(0, 60, N_E, dtype=torch.float64))
    scripted = torch.jit.script(pipe)
    with torch.no_grad():
        assert bool(pipe(foreign)[3].all())  # a 30 % signature off the modes: still out of distribution
        for a, b in zip(pipe(y), scripted(y)):
            torch.testing.assert_close(a, b, equal_nan=True)
        torch.testing.assert_close(pipe.gappy_residual_limit(y), scripted.gappy_residual_limit(y))
        samples = y.index_select(1, pipe.gappy.indices)  # no noise estimate: the largest threshold
        assert torch.equal(pipe.gappy_residual_limit(samples), torch.full((50,), values[-1], dtype=torch.float64))
