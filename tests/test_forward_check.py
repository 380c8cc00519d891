"""Analysis by synthesis: the forward surrogate k -> alpha, the consistency statistic, its place in the bundle and
the online pipeline (phm_torch/surrogates/forward.py, phm_torch/online/consistency.py)."""

from __future__ import annotations

import math

import pytest
import torch

from phm_torch.online import OnlinePipeline
from phm_torch.online.consistency import ConsistencyCheck, calibrate_consistency
from phm_torch.online.pipeline_consistency import attach_consistency, pipeline_basis
from phm_torch.params import load_actuator
from phm_torch.prognostics import DamageModel
from phm_torch.surrogates import POD, GappyPOD, SurrogateBundle, add_noise, rms
from phm_torch.surrogates.classifiers.polynomial_svm import PolynomialSVM
from phm_torch.surrogates.fdi_mlp import FDIMLP
from phm_torch.surrogates.forward import ForwardSurrogate, fit_forward_check
from phm_torch.surrogates.full_signal_check import FullSignalCheck

pytestmark = pytest.mark.torchscript  # scripts, saves or loads TorchScript on purpose

N_E, N_LATENT = 801, 10
WEIGHTS = torch.linspace(3.0, 0.6, N_LATENT, dtype=torch.float64)
NOMINAL = list(load_actuator().nominal_faults)


def _basis() -> torch.Tensor:
    t = torch.linspace(0.0, 1.0, N_E, dtype=torch.float64)
    cols = [
        torch.sin(2 * math.pi * (i + 1) * t * (1 + t)) * torch.exp(-(((t - (i + 0.5) / N_LATENT) / 0.25) ** 2))
        for i in range(N_LATENT)
    ]
    return torch.linalg.qr(torch.stack(cols, 1))[0]


def _latent(k: torch.Tensor) -> torch.Tensor:
    """(B, 10) smooth map of k with k7 a phase of the eccentricity k6, as the actuator's."""
    angle = 2 * math.pi * k[:, 6:7]
    return (
        torch.cat(
            [
                k[:, :6],
                k[:, 5:6] * torch.cos(angle),
                k[:, 5:6] * torch.sin(angle),
                k[:, :1] * k[:, 1:2],
                torch.sin(2.0 * k[:, 2:3]),
            ],
            1,
        )
        * WEIGHTS
    )


def _mean() -> torch.Tensor:
    t = torch.linspace(0.0, 1.0, N_E, dtype=torch.float64)
    return 5.0 + 2.0 * torch.sin(2 * math.pi * 3 * t)


def records(k: torch.Tensor) -> torch.Tensor:
    return _mean() + _latent(k) @ _basis().T


def faults(n: int, seed: int) -> torch.Tensor:
    k = torch.rand(n, 8, generator=torch.Generator().manual_seed(seed), dtype=torch.float64)
    k[:, 7] = 0.5 * k[:, 7]
    return k


class OracleFDI(torch.nn.Module):
    """alpha -> k inverting the synthetic map exactly (the latent amplitudes are linear in alpha)."""

    def __init__(self, pod: POD):
        super().__init__()
        v = _basis()
        self.register_buffer("to_latent", pod.modes_.T @ v / WEIGHTS)  # alpha -> latent / weights, (n_m, 10)
        self.register_buffer("offset", (pod.mean_ - _mean()) @ v / WEIGHTS)

    def forward(self, alpha: torch.Tensor) -> torch.Tensor:
        g = alpha @ self.to_latent + self.offset
        ecc = torch.sqrt(g[:, 6] ** 2 + g[:, 7] ** 2)
        phase = torch.remainder(torch.atan2(g[:, 7], g[:, 6]) / (2 * math.pi), 1.0)
        k = torch.cat([g[:, :6], phase.unsqueeze(1), torch.zeros_like(phase).unsqueeze(1)], 1)
        k[:, 5] = ecc
        return k.clamp(0.0, 1.0)


@pytest.fixture(scope="module")
def fitted():
    torch.set_num_threads(1)
    k = faults(1200, 0)
    y = records(k)
    pod = POD(N_LATENT).fit(y)
    gappy = GappyPOD(pod.modes_, pod.mean_, torch.linspace(0, N_E - 1, 24).round().long())
    fdi = OracleFDI(pod)
    model = fit_forward_check(pod, gappy, fdi, k, y, seed=0, max_epochs=250, patience=30, n_hidden=48)
    return pod, gappy, fdi, model


def test_forward_surrogate_fits_a_smooth_map_with_a_phase(fitted):
    pod, _, _, model = fitted
    k = faults(300, 5)
    with torch.no_grad():
        err = (model(k).double() - pod(records(k))).norm(dim=1) / model.alpha_scale_.double()
    assert float(model.error_ / model.alpha_scale_) < 0.05  # held-out, relative to the coefficients' spread
    assert float(err.median()) < 0.05
    assert model.best_epoch_ > 0 and 0 < float(model.floor_full_) < 0.05


def test_fit_is_deterministic_and_rejects_bad_arguments():
    k = faults(200, 1)
    alpha = _latent(k).float()
    a = ForwardSurrogate(N_LATENT, n_hidden=8, max_epochs=5).fit(k.float(), alpha)
    b = ForwardSurrogate(N_LATENT, n_hidden=8, max_epochs=5).fit(k.float(), alpha)
    torch.testing.assert_close(a(k.float()), b(k.float()), rtol=0, atol=0)
    with pytest.raises(ValueError, match="holdout"):
        ForwardSurrogate(N_LATENT, holdout=0.7)
    with pytest.raises(ValueError, match="alpha"):
        a.fit(k.float(), alpha[:, :3])


def _statistics(fitted, y: torch.Tensor, noise: torch.Tensor):
    pod, gappy, fdi, model = fitted
    check = ConsistencyCheck(model, pod.mean_, pod.modes_, gappy.indices)
    with torch.no_grad():
        k_hat = fdi(gappy(gappy.select(y))[0])
        return check.statistic(y, k_hat, noise), check.statistic(gappy.select(y), k_hat, noise)


def test_statistic_is_stable_across_noise_and_large_for_shifted_or_flipped_records(fitted):
    k = faults(200, 7)
    clean = records(k)
    medians, highs = [], []
    for level in (0.0, 0.01, 0.03):
        y = add_noise(clean, rms(clean), level, torch.Generator().manual_seed(3)) if level else clean
        full, _ = _statistics(fitted, y, torch.full((200,), level, dtype=torch.float64))
        medians.append(float(full.median()))
        highs.append(float(full.quantile(0.99)))
    assert all(0.4 < m < 2.5 for m in medians), medians  # ~1: residual at the noise (or the floor)
    assert max(highs) < 8.0, highs
    noise = torch.full((200,), 0.01, dtype=torch.float64)
    y = add_noise(clean, rms(clean), 0.01, torch.Generator().manual_seed(4))
    shifted = torch.roll(y, 20, dims=1)  # 1 ms at 20 kHz
    flipped = -y  # a probe the wrong way round
    for bad in (shifted, flipped):
        full, sel = _statistics(fitted, bad, noise)
        assert float(full.median()) > 3 * max(highs), float(full.median())
        assert float(sel.median()) > 1.5 * max(highs), float(sel.median())


def _damage() -> DamageModel:
    f = torch.diag(torch.tensor([5e-4] * 6 + [0.0, 3e-4], dtype=torch.float64))
    return DamageModel(f.tolist(), [1e-6] * 6 + [0.0, 1e-6], 100.0, 20000.0, 50.0, NOMINAL)


def _pipeline(fitted, with_check: bool) -> OnlinePipeline:
    pod, gappy, fdi, model = fitted
    k = faults(300, 2)
    clf = PolynomialSVM(degree=2).fit(k, k[:, :5].amax(1) < 0.5)
    check = ConsistencyCheck(model, pod.mean_, pod.modes_, gappy.indices) if with_check else None
    return OnlinePipeline(
        gappy,
        fdi,
        clf,
        _damage(),
        torch.tensor([0.02, 0.0, -0.02]),
        torch.ones(8),
        N_E,
        residual_threshold=1e3,
        consistency=check,
    ).eval()


def test_pipeline_flags_inconsistent_records_scripted_as_eager_and_without_check_as_before(fitted):
    pipe, plain = _pipeline(fitted, True), _pipeline(fitted, False)
    clean = records(faults(150, 9))
    cal = calibrate_consistency(pipe, clean, [0.01, 0.03, 0.1], seed=0, quantile=0.98)
    assert len(cal["thresholds"]) == 2 and len(cal["thresholds"][0]) == 3
    test = records(faults(40, 11))
    y = add_noise(test, rms(test), 0.01, torch.Generator().manual_seed(5))
    bad = torch.cat([y, torch.roll(y, 20, dims=1), -y])
    scripted, scripted_plain = torch.jit.script(pipe), torch.jit.script(plain)
    with torch.no_grad():
        out, again, before = pipe(bad), scripted(bad), plain(bad)
        for a, b in zip(out, again):
            torch.testing.assert_close(a, b, atol=1e-5, rtol=1e-5, equal_nan=True)
        torch.testing.assert_close(pipe.consistency(bad), scripted.consistency(bad), atol=1e-5, rtol=1e-5)
        for a, b in zip(before, scripted_plain(bad)):
            torch.testing.assert_close(a, b, atol=1e-5, rtol=1e-5, equal_nan=True)
        margin = pipe.consistency(bad)
        samples = pipe.consistency(bad.index_select(1, pipe.gappy.indices), torch.full((120,), 0.01))
    ood, ood_plain = out[3], before[3]
    assert not bool(ood_plain.any())  # nothing else flags these records
    assert float(ood[:40].double().mean()) <= 0.05  # the good ones pass
    assert bool(ood[40:].all()) and bool((margin[40:] > 1).all())  # shifted and flipped: inconsistent
    assert float((samples[40:] > 1).double().mean()) > 0.9 and float((samples[:40] > 1).double().mean()) <= 0.05
    torch.testing.assert_close(out[0], before[0])  # k_hat, score untouched
    torch.testing.assert_close(out[1], before[1])
    assert bool(torch.isnan(scripted_plain.consistency(bad)).all())


def test_bundle_round_trip_with_and_without_forward_model(fitted, tmp_path):
    pod, gappy, _, model = fitted
    k = faults(300, 2)
    clf = PolynomialSVM(degree=2).fit(k, k[:, :5].amax(1) < 0.5)
    net = FDIMLP(N_LATENT, 6)
    net.set_normalization(pod(records(k)).float())
    bundle = SurrogateBundle(pod, gappy.indices, net, clf, 20000.0)
    bundle.save(tmp_path / "plain.pt")
    assert SurrogateBundle.load(tmp_path / "plain.pt").forward_model is None
    bundle.forward_model = model
    bundle.save(tmp_path / "fwd.pt")
    back = SurrogateBundle.load(tmp_path / "fwd.pt")
    k_test = faults(20, 3).float()
    with torch.no_grad():
        torch.testing.assert_close(back.forward_model(k_test), model(k_test))
    assert float(back.forward_model.floor_full_) == float(model.floor_full_)
    pipe = OnlinePipeline.from_bundle(back, _damage(), torch.zeros(3), torch.ones(8))
    assert (
        pipe.has_consistency
        and not OnlinePipeline.from_bundle(
            SurrogateBundle.load(tmp_path / "plain.pt"), _damage(), torch.zeros(3), torch.ones(8)
        ).has_consistency
    )


def _pipeline_with_rows(fitted) -> OnlinePipeline:
    """A pipeline without a consistency check whose full-record check reads every 16th sample, its gappy layer every
    8th: the two share every 16th, enough to recover the basis at the rows."""
    pod, _, fdi, _ = fitted
    gappy = GappyPOD(pod.modes_, pod.mean_, torch.arange(0, N_E, 8))
    k = faults(300, 2)
    clf = PolynomialSVM(degree=2).fit(k, k[:, :5].amax(1) < 0.5)
    check = FullSignalCheck(
        pod.modes_, pod.mean_, residual_threshold=1e3, roughness_threshold=1e3, plateau_threshold=1.0
    )
    return OnlinePipeline(
        gappy, fdi, clf, _damage(), torch.tensor([0.02, 0.0, -0.02]), torch.ones(8), N_E, 1e3, full_check=check
    ).eval()


def test_a_pipeline_without_its_bundle_gets_a_consistency_check_from_its_own_basis(fitted):
    """scripts/add_consistency_check.py's library part: the POD basis at the rows is recovered from the full-record
    check's orthonormalised basis and the gappy modes (exactly), and the fitted check flags shifted and flipped
    records, scripted as eager, while good ones pass."""
    pod, *_ = fitted
    pipe = _pipeline_with_rows(fitted)
    mean, modes = pipeline_basis(pipe)
    rows, idx = torch.arange(0, N_E, 16), pipe.gappy.indices
    for at in (rows, idx):
        torch.testing.assert_close(mean[at], pod.mean_[at].double(), atol=1e-9, rtol=0)
        torch.testing.assert_close(modes[at], pod.modes_[at].double(), atol=1e-9, rtol=0)
    assert bool(torch.isnan(mean[1:8]).all())  # nothing else is known
    k = faults(1200, 0)
    attach_consistency(pipe, k, records(k), seed=0, max_epochs=250, patience=30, n_hidden=48)
    assert pipe.has_consistency
    calibrate_consistency(pipe, records(faults(150, 9)), [0.01, 0.03, 0.1], seed=0, quantile=0.98)
    test = records(faults(40, 11))
    y = add_noise(test, rms(test), 0.01, torch.Generator().manual_seed(5))
    bad = torch.cat([y, torch.roll(y, 20, dims=1), -y])
    scripted = torch.jit.script(pipe)
    with torch.no_grad():
        margin = pipe.consistency(bad)
        torch.testing.assert_close(margin, scripted.consistency(bad), atol=1e-5, rtol=1e-5)
    assert float((margin[:40] > 1).double().mean()) <= 0.05 and bool((margin[40:] > 1).all())
    with pytest.raises(ValueError, match="share 0 samples"):
        pipe.gappy = GappyPOD(pod.modes_, pod.mean_, torch.arange(1, N_E, 16))
        pipeline_basis(pipe)


def test_recalibration_at_a_higher_quantile_raises_the_thresholds_and_nothing_else(fitted):
    """scripts/recalibrate_consistency.py's library part: a higher quantile raises every threshold, flags no more of
    the held-out records, and leaves every other output as it was; bad arguments are one-line errors."""
    from phm_torch.online.consistency import recalibrate_consistency

    pipe = _pipeline(fitted, True)
    clean = records(faults(300, 9))
    calibrate_consistency(pipe, clean[:150], [0.01, 0.03, 0.1], seed=0, quantile=0.9)
    low = pipe.consistency_check.thresholds.clone()
    probe = add_noise(clean[200:], rms(clean[200:]), 0.01, torch.Generator().manual_seed(5))
    with torch.no_grad():
        before = pipe(probe)
    report = recalibrate_consistency(pipe, clean, 0.99, seed=0, calibrate_records=150)
    assert bool((pipe.consistency_check.thresholds > low).all())
    assert report["after"]["calibration"]["quantile"] == 0.99
    for level, rates in report["after"]["flag_rates"].items():
        assert rates["inconsistent"] <= report["before"]["flag_rates"][level]["inconsistent"]
    assert report["before"]["flag_rates"]["0.01"]["inconsistent"] > 0.0  # at 0.9 some held-out records were flagged
    with torch.no_grad():
        after = pipe(probe)
    for i in (0, 1, 4):  # k_hat, score, residual
        torch.testing.assert_close(after[i], before[i])
    assert int(after[3].sum()) < int(before[3].sum())  # fewer flags: the RUL of the records no longer flagged
    kept = ~(after[3] | before[3])  # is no longer NaN; where neither is flagged it is the same
    torch.testing.assert_close(after[2][kept], before[2][kept])
    with pytest.raises(ValueError, match="calibrate_records must be in"):
        recalibrate_consistency(pipe, clean, 0.99, seed=0, calibrate_records=295)
    with pytest.raises(ValueError, match="no consistency check"):
        recalibrate_consistency(_pipeline(fitted, False), clean, 0.99, seed=0, calibrate_records=150)
