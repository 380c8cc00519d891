"""POD layer: subspace, energy spectrum, solvers, projection, errors."""

from __future__ import annotations

import pytest
import torch
from surrogate_data import N_LATENT, basis, faults, signals

from phm_torch.surrogates import POD


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
    assert bool((e[:-1] >= e[1:] - 1e-9).all())                 # decreasing
    cum = pod.cumulative_energy()
    assert 0.999 < float(cum[N_LATENT - 1]) <= 1.0 + 1e-6       # rank-10 family + weak noise
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
    pod = POD(2)
    with pytest.raises(ValueError, match="not fitted"):
        pod(torch.randn(3, 50))
    pod.fit(torch.randn(10, 50))
    with pytest.raises(ValueError, match="50 samples"):
        pod(torch.randn(3, 49))
