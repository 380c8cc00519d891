"""Gappy POD layer: exact recovery in the span, masking of missing samples, gradients, scripting."""

from __future__ import annotations

import math

import pytest
import torch
from surrogate_data import N_LATENT, faults, signals

from phm_torch.surrogates import POD, GappyPOD, drop_samples
from phm_torch.surrogates.gappy_pod import WOODBURY_MAX
from phm_torch.surrogates.selectors import build_selector

pytestmark = pytest.mark.torchscript  # scripts, saves or loads TorchScript on purpose


@pytest.fixture(scope="module")
def pod() -> POD:
    return POD(N_LATENT).fit(signals(faults(300, 0)).double())


@pytest.fixture(scope="module")
def in_span(pod) -> torch.Tensor:
    """Noise-free signals inside the span of the modes (B, n_e), float64."""
    alpha = torch.randn(16, N_LATENT, generator=torch.Generator().manual_seed(5), dtype=torch.float64) * 10
    return pod.reconstruct(alpha)


def test_all_points_recover_the_full_projection(pod, in_span):
    gappy = GappyPOD(pod.modes_, pod.mean_, torch.arange(pod.modes_.shape[0]))
    alpha, resid = gappy(gappy.select(in_span))
    assert torch.allclose(alpha, pod(in_span), atol=1e-9)
    assert float(resid.max()) < 1e-9


@pytest.mark.parametrize("name", ["qdeim", "greedy", "uniform", "som"])
def test_selected_points_recover_in_span_signals(pod, in_span, name):
    idx = build_selector(name, n_points=15).fit(pod.modes_).indices_
    gappy = GappyPOD(pod.modes_, pod.mean_, idx)
    alpha, resid = gappy(gappy.select(in_span))
    assert torch.allclose(alpha, pod(in_span), atol=1e-7)
    assert float(resid.max()) < 1e-8


def test_residual_flags_signals_outside_the_span(pod, in_span):
    gappy = GappyPOD(pod.modes_, pod.mean_, build_selector("greedy", n_points=20).fit(pod.modes_).indices_)
    off = in_span + 0.5 * torch.sin(torch.arange(in_span.shape[1], dtype=torch.float64) * 1.7)  # not in the span
    _, r_in = gappy(gappy.select(in_span))
    _, r_off = gappy(gappy.select(off))
    assert float(r_off.min()) > 100 * float(r_in.max())


def test_missing_samples_are_dropped_from_that_signal_only(pod, in_span):
    idx = build_selector("greedy", n_points=20).fit(pod.modes_).indices_
    gappy = GappyPOD(pod.modes_, pod.mean_, idx)
    noisy = gappy.select(in_span) + 0.05 * torch.randn(
        16, 20, generator=torch.Generator().manual_seed(0), dtype=torch.float64
    )
    holed = drop_samples(noisy, torch.tensor([0, 3] + [0] * 14), torch.Generator().manual_seed(1))
    alpha, _ = gappy(holed)
    full, _ = gappy(noisy)
    assert torch.allclose(alpha[0], full[0]) and torch.allclose(alpha[2:], full[2:])
    keep = torch.isfinite(holed[1])
    ref = torch.linalg.lstsq(gappy.modes_hat[keep], (noisy[1] - gappy.mean_hat)[keep]).solution
    assert torch.allclose(alpha[1], ref, atol=1e-9)
    # A boolean mask is the same as NaN.
    masked, _ = gappy(noisy, torch.isfinite(holed))
    assert torch.allclose(masked, alpha)


@pytest.mark.parametrize("n_points", [30, 200])
def test_few_missing_samples_by_the_woodbury_identity(pod, in_span, n_points):
    """Up to WOODBURY_MAX samples missing: the complete G^-1 updated by the Woodbury identity, the same
    least squares as on the present samples (float64 exactly, float32 closely); more: a G per signal."""
    idx = build_selector("uniform", n_points=n_points).fit(pod.modes_).indices_
    gappy = GappyPOD(pod.modes_, pod.mean_, idx)
    noisy = gappy.select(in_span) + 0.05 * torch.randn(
        16, n_points, generator=torch.Generator().manual_seed(2), dtype=torch.float64
    )
    counts = torch.arange(16) % (WOODBURY_MAX + 1)
    holed = drop_samples(noisy, counts, torch.Generator().manual_seed(3))
    alpha, resid = gappy(holed)
    for row in range(16):
        keep = torch.isfinite(holed[row])
        ref = torch.linalg.lstsq(gappy.modes_hat[keep], (noisy[row] - gappy.mean_hat)[keep]).solution
        assert torch.allclose(alpha[row], ref, atol=1e-9)
        fit = gappy.mean_hat[keep] + gappy.modes_hat[keep] @ ref
        assert float(resid[row]) == pytest.approx(float((noisy[row][keep] - fit).pow(2).mean().sqrt()), rel=1e-9)
    single = GappyPOD(pod.modes_.float(), pod.mean_.float(), idx)
    a32, _ = single(holed.float())
    assert float((a32.double() - alpha).abs().max()) < 1e-4 * float(alpha.abs().max())
    # more missing in one signal: the per-signal matrices, the same solution
    many = holed.clone()
    many[0, : WOODBURY_MAX + 1] = float("nan")
    keep = torch.isfinite(many[0])
    ref = torch.linalg.lstsq(gappy.modes_hat[keep], (noisy[0] - gappy.mean_hat)[keep]).solution
    assert torch.allclose(gappy(many)[0][0], ref, atol=1e-9)


def test_gradients(pod, in_span):
    idx = build_selector("greedy", n_points=14).fit(pod.modes_).indices_
    gappy = GappyPOD(pod.modes_, pod.mean_, idx)
    x = gappy.select(in_span[:3]).clone().requires_grad_(True)
    assert torch.autograd.gradcheck(lambda s: gappy(s)[0], (x,))
    mask = torch.ones(3, 14, dtype=torch.bool)
    mask[1, 2] = False
    assert torch.autograd.gradcheck(lambda s: gappy(s, mask)[0], (x,))
    # NaN samples get a zero gradient, the others a finite one.
    y = x.detach().clone()
    y[0, 4] = float("nan")
    y.requires_grad_(True)
    gappy(y)[0].sum().backward()
    assert bool(torch.isfinite(y.grad).all()) and float(y.grad[0, 4]) == 0.0


def test_torchscript(pod, in_span):
    gappy = GappyPOD(pod.modes_, pod.mean_, build_selector("qdeim", n_points=12).fit(pod.modes_).indices_)
    scripted = torch.jit.script(gappy)
    s = gappy.select(in_span)
    s[0, 0] = float("nan")
    a, r = scripted(s)
    b, q = gappy(s)
    assert torch.allclose(a, b) and torch.allclose(r, q)
    assert gappy.noise_covariance.numel() == 0  # least squares carries no (n_w, n_w) matrix


def test_condition_number(pod):
    good = GappyPOD(pod.modes_, pod.mean_, build_selector("greedy", n_points=20).fit(pod.modes_).indices_)
    assert 1.0 <= good.condition_number() < 1e3


def test_bad_input(pod):
    with pytest.raises(ValueError, match="n_points=5 < n_modes=10"):
        GappyPOD(pod.modes_, pod.mean_, torch.arange(5))
    gappy = GappyPOD(pod.modes_, pod.mean_, torch.arange(0, 800, 50))  # 16 points
    with pytest.raises(ValueError, match=r"samples must be \(B, 16\)"):
        gappy(torch.zeros(2, 15, dtype=torch.float64))
    s = torch.zeros(2, 16, dtype=torch.float64)
    s[1, :7] = float("nan")  # 9 present samples for 10 modes
    alpha, resid = gappy(s)
    assert bool(torch.isfinite(alpha[0]).all()) and bool(torch.isnan(alpha[1]).all())
    assert math.isfinite(float(resid[0])) and float(resid[1]) == float("inf")
    x = s.clone().requires_grad_(True)
    gappy(x)[0][0].sum().backward()  # the singular signal does not poison gradients
    assert bool(torch.isfinite(x.grad).all())
    ridged = GappyPOD(pod.modes_, pod.mean_, torch.arange(0, 800, 50), ridge=1e-3)
    assert bool(torch.isfinite(ridged(s)[0]).all())
    with pytest.raises(ValueError, match="indices must lie in"):
        GappyPOD(pod.modes_, pod.mean_, torch.tensor([0, 900]))


# ---- Bayesian gappy layer ------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def truncated():
    """A rank-10 family seen through 4 modes and 9 points: the 6 truncated modes alias into plain LS."""
    train, test = signals(faults(3000, 1), 0.02, 1).double(), signals(faults(400, 2), 0.02, 2).double()
    pod = POD(4).fit(train)
    idx = build_selector("qdeim", n_points=9).fit(pod.modes_).indices_
    return pod, idx, train, test


def test_bayesian_layer_is_the_least_squares_regression_of_the_training_coefficients(truncated):
    from phm_torch.surrogates.gappy_pod import gappy_statistics

    pod, idx, train, _ = truncated
    stats = gappy_statistics(train, pod.modes_, pod.mean_, idx)
    gappy = GappyPOD(pod.modes_, pod.mean_, idx, **stats)
    alpha, _ = gappy(gappy.select(train))
    samples = gappy.select(train) - pod.mean_[idx]
    regression = samples @ torch.linalg.lstsq(samples, pod(train)).solution
    torch.testing.assert_close(alpha, regression, atol=1e-8, rtol=1e-8)


def test_bayesian_layer_beats_least_squares_on_unseen_signals(truncated):
    from phm_torch.surrogates.gappy_pod import gappy_statistics
    from phm_torch.surrogates.metrics import err_alpha

    pod, idx, train, test = truncated
    plain = GappyPOD(pod.modes_, pod.mean_, idx)
    bayes = GappyPOD(pod.modes_, pod.mean_, idx, **gappy_statistics(train, pod.modes_, pod.mean_, idx, 0.02))
    full = pod(test)
    e_plain = float(err_alpha(plain(plain.select(test))[0], full).median())
    e_bayes = float(err_alpha(bayes(bayes.select(test))[0], full).median())
    assert e_bayes < 0.8 * e_plain, (e_bayes, e_plain)


def test_bayesian_missing_samples_drop_their_rows_and_columns_of_r(truncated):
    from phm_torch.surrogates.gappy_pod import gappy_statistics

    pod, idx, train, test = truncated
    stats = gappy_statistics(train, pod.modes_, pod.mean_, idx, 0.02)
    gappy = GappyPOD(pod.modes_, pod.mean_, idx, **stats)
    samples = gappy.select(test[:6])
    keep = torch.tensor([0, 1, 3, 4, 6, 8])
    holed = samples.clone()
    holed[:, [2, 5, 7]] = float("nan")
    alpha, resid = gappy(holed)
    sub = GappyPOD(
        pod.modes_,
        pod.mean_,
        idx[keep],
        noise_covariance=stats["noise_covariance"][keep][:, keep],
        prior_variance=stats["prior_variance"],
    )
    alpha_sub, resid_sub = sub(samples[:, keep])
    torch.testing.assert_close(alpha, alpha_sub, atol=1e-9, rtol=1e-9)
    torch.testing.assert_close(resid, resid_sub, atol=1e-9, rtol=1e-9)
    # fewer present samples than modes is still a posterior (the prior regularises it)
    few = samples.clone()
    few[:, 3:] = float("nan")
    assert bool(torch.isfinite(gappy(few)[0]).all())
    scripted = torch.jit.script(gappy)
    torch.testing.assert_close(scripted(holed)[0], alpha)
    torch.testing.assert_close(scripted(samples)[0], gappy(samples)[0])


def test_bayesian_bad_statistics(truncated):
    pod, idx, _, _ = truncated
    with pytest.raises(ValueError, match="both noise_covariance and prior_variance"):
        GappyPOD(pod.modes_, pod.mean_, idx, noise_covariance=torch.eye(9, dtype=torch.float64))
    with pytest.raises(ValueError, match=r"must be \(9, 9\) and prior_variance \(4,\)"):
        GappyPOD(pod.modes_, pod.mean_, idx, noise_covariance=torch.eye(8), prior_variance=torch.ones(4))
    with pytest.raises(ValueError, match="positive definite"):
        GappyPOD(pod.modes_, pod.mean_, idx, noise_covariance=-torch.eye(9), prior_variance=torch.ones(4))
