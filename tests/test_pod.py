"""POD layer: subspace, energy spectrum, solvers, projection, errors."""

from __future__ import annotations

import pytest
import torch
from surrogate_data import N_LATENT, basis, faults, signals

from phm_torch.surrogates import POD
from phm_torch.surrogates.randomized_svd import centred_mean_and_energy, randomized_svd_centred


@pytest.fixture(scope="module")
def data() -> torch.Tensor:
    return signals(faults(300, 0), noise=0.01)


def test_modes_span_the_signal_family_and_are_orthonormal(data):
    pod = POD(N_LATENT).fit(data)
    v = pod.modes_.to(torch.float64)
    assert torch.allclose(v.T @ v, torch.eye(N_LATENT, dtype=torch.float64), atol=1e-5)
    # The true basis lies in the span of the modes (up to the noise).
    true = basis()
    residual = true - v @ (v.T @ true)
    assert float(residual.norm() / true.norm()) < 0.02


def test_energy_spectrum(data):
    pod = POD(N_LATENT, n_spectrum=40).fit(data)
    e = pod.energy_.to(torch.float64)
    assert e.shape == (40,)
    assert bool((e[:-1] >= e[1:] - 1e-9).all())  # decreasing
    cum = pod.cumulative_energy()
    assert 0.999 < float(cum[N_LATENT - 1]) <= 1.0 + 1e-6  # rank-10 family + weak noise
    assert float(cum[-1]) <= 1.0 + 1e-6
    # Energy fraction = s^2 / ||Y - mean||_F^2
    yc = data.double() - data.double().mean(0)
    assert float(e[0]) == pytest.approx(float(pod.singular_values_[0].double() ** 2 / yc.pow(2).sum()), rel=1e-4)


@pytest.mark.parametrize("solver", ["full", "randomized"])
def test_solvers_agree(data, solver):
    ref = POD(6, solver="snapshots").fit(data)
    other = POD(6, solver=solver).fit(data)
    overlap = (ref.modes_.double() * other.modes_.double()).sum(0)
    assert torch.allclose(overlap, torch.ones(6, dtype=torch.float64), atol=1e-4)  # same modes, same signs
    assert torch.allclose(ref.singular_values_[:6], other.singular_values_[:6], rtol=1e-4)


def test_fit_leaves_float64_snapshots_untouched(data):
    # the fit centres one float64 copy in place: the caller's float64 array must not be that copy
    snapshots = data.double()
    before = snapshots.clone()
    pod = POD(N_LATENT).fit(snapshots)
    assert torch.equal(snapshots, before)
    assert torch.allclose(pod.mean_, before.mean(0), atol=1e-12)


@pytest.mark.parametrize("n_e", [None, 120])  # wide (n_s < n_e) and tall (n_s > n_e) orientations
def test_streamed_randomized_svd_is_torch_svd_lowrank(data, n_e):
    # the same algorithm and random draw as torch.svd_lowrank on the centred float64 copy it replaces,
    # summed over uneven row blocks of the float32 snapshots
    y = data if n_e is None else data[:, :n_e].contiguous()
    assert (y.shape[0] < y.shape[1]) == (n_e is None)
    yc = y.double() - y.double().mean(0)
    torch.manual_seed(3)
    _, s_ref, v_ref = torch.svd_lowrank(yc, q=25, niter=4)
    mean, energy = centred_mean_and_energy(y, block_rows=7)
    assert torch.allclose(mean, y.double().mean(0), rtol=0, atol=1e-12)
    assert energy == pytest.approx(float(yc.pow(2).sum()), rel=1e-12)
    torch.manual_seed(3)
    s, v = randomized_svd_centred(y, mean, q=25, n_iter=4, block_rows=7)
    assert v.shape == (y.shape[1], 25) and s.dtype == torch.float64
    assert torch.allclose(s, s_ref, rtol=1e-9)
    k = N_LATENT  # well-separated singular values: the vectors are unique up to sign
    assert torch.allclose((v[:, :k] * v_ref[:, :k]).sum(0).abs(), torch.ones(k, dtype=torch.float64), atol=1e-9)


def test_randomized_pod_does_not_depend_on_the_block_size(data):
    one = POD(N_LATENT, solver="randomized", block_rows=1).fit(data)
    whole = POD(N_LATENT, solver="randomized", block_rows=10_000).fit(data)
    for name in ("mean_", "modes_", "singular_values_", "energy_"):
        assert torch.allclose(getattr(one, name), getattr(whole, name), rtol=1e-5, atol=1e-6), name


def test_projection_and_reconstruction(data):
    pod = POD(N_LATENT).fit(data)
    alpha = pod(data)
    assert alpha.shape == (300, N_LATENT)
    rec = pod.reconstruct(alpha)
    rel = (rec - data).norm() / (data - pod.mean_).norm()
    assert float(rel) < 0.02
    trunc = pod.truncated(4)
    assert torch.allclose(trunc(data), alpha[:, :4], atol=1e-4)


def test_bad_input():
    with pytest.raises(ValueError, match="n_modes must be a positive integer"):
        POD(0)
    with pytest.raises(ValueError, match="pod.solver"):
        POD(3, solver="qr")
    with pytest.raises(ValueError, match="exceeds the rank"):
        POD(10).fit(torch.randn(5, 50))
    with pytest.raises(ValueError, match="NaN"):
        POD(2).fit(torch.tensor([[1.0, float("nan"), 2.0], [0.0, 1.0, 2.0], [3.0, 1.0, 0.0]]))
    late_nan = torch.randn(9, 20)
    late_nan[8, 3] = float("inf")
    with pytest.raises(ValueError, match="NaN or inf"):  # in the last of several blocks
        POD(2, solver="randomized", block_rows=4).fit(late_nan)
    with pytest.raises(ValueError, match="pod.block_rows"):
        POD(2, block_rows=0)
    pod = POD(2)
    with pytest.raises(ValueError, match="not fitted"):
        pod(torch.randn(3, 50))
    pod.fit(torch.randn(10, 50))
    with pytest.raises(ValueError, match="50 samples"):
        pod(torch.randn(3, 49))
