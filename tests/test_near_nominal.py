"""The near-nominal FDI of life tracking (phm_torch.tracking.near_nominal): it learns coefficients -> k near nominal,
its half-widths are its held-out rms, it is read only where the pipeline's own estimate is near nominal and the
noise low, it round-trips through its file (weights_only) and refuses another pipeline."""

from __future__ import annotations

import copy
import math

import pytest
import torch
from test_tracking import make_pipeline

from phm_torch.faults import FAULT_NAMES
from phm_torch.tracking.near_nominal import NearNominalFDI, fit_near_nominal
from phm_torch.tracking.response import probe_k_hat

N_MODES = 10


def synthetic(n: int, seed: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Near-nominal k (every damage below 0.2) and coefficients linear in it with a little noise."""
    g = torch.Generator().manual_seed(seed)
    k = torch.rand(n, 8, generator=g, dtype=torch.float64) * 0.2
    k[:, 6] = torch.rand(n, generator=g, dtype=torch.float64)
    k[:, 7] = 0.5 + (k[:, 7] - 0.1) * 0.2
    mix = torch.randn(8, N_MODES, generator=torch.Generator().manual_seed(99), dtype=torch.float64)
    mix[6] = 0.0  # the phase is not seen
    return k @ mix + 0.0005 * torch.randn(n, N_MODES, generator=g, dtype=torch.float64), k


@pytest.fixture(scope="module")
def fitted() -> NearNominalFDI:
    alpha, k = synthetic(3000, 0)
    net = NearNominalFDI(N_MODES, n_hidden=32, gate=0.25, noise_levels=(0.01, 0.02))
    fit_near_nominal(net, alpha, torch.full((3000,), 0.01, dtype=torch.float64), k, steps=3000, lr=3e-3)
    alpha_cal, k_cal = synthetic(500, 1)
    for level, noise in enumerate((0.01, 0.02)):
        net.calibrate(level, alpha_cal, k_cal, k_cal, torch.full((500,), noise, dtype=torch.float64))
    net.provenance = {"probe_k_hat": probe_k_hat(make_pipeline()), "source": "synthetic"}
    return net


def test_it_learns_near_nominal_k_and_its_half_widths_are_its_held_out_error(fitted):
    alpha, k = synthetic(500, 2)
    with torch.no_grad():
        err = (fitted(alpha, torch.full((500,), 0.01, dtype=torch.float64)) - k)[:, [0, 1, 2, 3, 4, 5, 7]]
    rms = err.pow(2).mean(0).sqrt()
    assert float(rms.max()) < 0.01  # against a 0.2 range
    widths = fitted.half_widths_[0, [0, 1, 2, 3, 4, 5, 7]]
    # between the calibrated levels the widths are interpolated, held beyond them
    mid = fitted.half_widths(torch.tensor([0.005, 0.015, 0.03], dtype=torch.float64))
    assert torch.allclose(mid[0], fitted.half_widths_[0]) and torch.allclose(mid[2], fitted.half_widths_[1])
    assert torch.allclose(mid[1], fitted.half_widths_.mean(0))
    assert torch.allclose(widths / 1.645, rms, rtol=0.3)  # calibrated on another draw of the same records
    inside = (err.abs() <= widths).double().mean()
    assert 0.83 < float(inside) < 0.97  # ~90 %


def test_it_is_read_only_near_nominal_at_low_noise(fitted):
    alpha, k = synthetic(4, 3)
    k_pipeline = k.clone()
    k_pipeline[1, 2] = 0.4  # the pipeline sees a large short: its own estimate stands
    noise = torch.tensor([0.01, 0.01, 0.05, 0.01], dtype=torch.float64)  # record 2 too noisy
    used, out, lower, upper = fitted.read(alpha, k_pipeline, noise)
    assert used.tolist() == [True, False, False, True]
    assert torch.equal(out[1], k_pipeline[1]) and math.isnan(float(lower[1, 0]))
    assert float(out[0, 6]) == float(k_pipeline[0, 6])  # the phase is always the pipeline's
    assert bool((upper[0] >= out[0]).all()) and bool((lower[0] <= out[0]).all())


def test_it_round_trips_and_refuses_another_pipeline(fitted, tmp_path):
    fitted.save(tmp_path / "nn.pt")
    again = NearNominalFDI.load(tmp_path / "nn.pt")
    alpha, _ = synthetic(8, 4)
    with torch.no_grad():
        noise = torch.full((8,), 0.01, dtype=torch.float64)
        assert torch.equal(again(alpha, noise), fitted(alpha, noise))
    pipe = make_pipeline()  # 6 modes
    with pytest.raises(ValueError, match="reads 10 coefficients, the synthetic pipeline has 6"):
        again.check_for(pipe, "the synthetic pipeline")
    small = NearNominalFDI(6, n_hidden=8)
    small.provenance = {"probe_k_hat": probe_k_hat(pipe)}
    small.check_for(pipe, "the synthetic pipeline")
    small.provenance["probe_k_hat"] = [v + 0.01 for v in small.provenance["probe_k_hat"]]
    with pytest.raises(ValueError, match="trained for another pipeline"):
        small.check_for(pipe, "the synthetic pipeline")
    (tmp_path / "bad.pt").write_bytes(b"not a file of ours")
    with pytest.raises(ValueError, match="cannot read it"):
        NearNominalFDI.load(tmp_path / "bad.pt")
    uncalibrated = NearNominalFDI(N_MODES, n_hidden=8)
    with pytest.raises(ValueError, match="not calibrated"):
        uncalibrated.read(alpha, torch.zeros(8, 8, dtype=torch.float64), torch.zeros(8, dtype=torch.float64))
    with pytest.raises(ValueError, match=r"near_nominal.gate must be in \(0, 1\]"):
        NearNominalFDI(N_MODES, gate=0.0)
    with pytest.raises(ValueError, match="noise_levels must be positive and increasing"):
        NearNominalFDI(N_MODES, noise_levels=(0.02, 0.01))


def test_only_the_records_the_gate_admits_calibrate_it(fitted):
    alpha, k = synthetic(400, 5)
    k_pipeline = k.clone()
    k_pipeline[:100, 3] = 0.6  # outside the gate: their (here wild) errors must not widen the intervals
    alpha = alpha.clone()
    alpha[:100] += 5.0
    before = fitted.half_widths_.clone()
    try:
        rms, n = fitted.calibrate(0, alpha, k, k_pipeline, torch.full((400,), 0.01, dtype=torch.float64))
        assert n == 300 and float(rms[[0, 1, 2, 3, 4, 5, 7]].max()) < 0.01
        with pytest.raises(ValueError, match="3 held-out records within the gate, 20 needed"):
            fitted.calibrate(
                0, alpha[200:203], k[200:203], k_pipeline[200:203], torch.full((3,), 0.01, dtype=torch.float64)
            )
    finally:
        fitted.half_widths_.copy_(before)


def test_a_full_record_network_projects_every_sample_on_an_orthonormal_basis(tmp_path):
    """Its basis holds the training records' principal directions, orthonormal, so white noise of std sigma per
    sample is white of std sigma on each coefficient (what the fit adds); a record it cannot read (a NaN sample, or
    another length) is refused or marked, and the file round-trips with its basis."""
    n_full, n_modes = 200, 4
    g = torch.Generator().manual_seed(7)
    shapes = torch.randn(3, n_full, generator=g, dtype=torch.float64)
    records = torch.randn(300, 3, generator=g, dtype=torch.float64) @ shapes + 2.0
    net = NearNominalFDI(n_modes, n_hidden=8, noise_levels=(0.01,), n_full=n_full)
    explained = net.fit_basis(records)
    basis = net.basis_.double()  # stored in float32
    assert torch.allclose(basis.T @ basis, torch.eye(n_modes, dtype=torch.float64), atol=1e-6)
    assert float(explained[:3].sum()) == pytest.approx(1.0, abs=1e-9)  # three shapes: three directions hold it all
    alpha, readable = net.coefficients(None, records)
    assert bool(readable.all())
    back = alpha[:, :3] @ basis[:, :3].T + net.record_mean_
    assert torch.allclose(back, records, atol=1e-5)  # the records lie in the basis's span
    sigma = 0.3
    noise = sigma * torch.randn(4000, n_full, generator=g, dtype=torch.float64)
    coeff_std = (noise @ basis).std(0)
    assert torch.allclose(coeff_std, torch.full((n_modes,), sigma, dtype=torch.float64), rtol=0.05)
    holed = records[:3].clone()
    holed[1, -4:] = float("nan")  # 2 % missing (a record aligned on its trigger): least squares on the rest
    holed[2, 3:20] = float("nan")  # 8.5 %: not readable
    alpha, readable = net.coefficients(None, holed)
    assert readable.tolist() == [True, True, False] and bool(torch.isfinite(alpha).all())
    full = net.coefficients(None, records[:3])[0]
    assert torch.allclose(alpha[:2], full[:2], atol=1e-6) and bool((alpha[2] == 0).all())  # in the span: exact
    noisy = records[:1] + sigma * torch.randn(1, n_full, generator=g, dtype=torch.float64)
    gap = noisy.clone()
    gap[0, -4:] = float("nan")
    drift = net.coefficients(None, gap)[0] - net.coefficients(None, noisy)[0]
    assert float(drift.abs().max()) < sigma  # four samples fewer: a fraction of one sample's noise on a coefficient
    with pytest.raises(ValueError, match=r"records \(B, 200\) expected, got \(2, 199\)"):
        net.coefficients(None, records[:2, :199])
    with pytest.raises(ValueError, match="n_full must be an integer above n_modes"):
        NearNominalFDI(n_modes, n_full=3)
    before = net.coefficients(None, records[:2])[0]
    net.basis_.mul_(-1.0)  # a basis changed in place after a projection: the next one reads it, not a stale copy
    assert torch.allclose(net.coefficients(None, records[:2])[0], -before)
    net.basis_.mul_(-1.0)
    net.provenance = {"probe_k_hat": probe_k_hat(make_pipeline())}
    net.save(tmp_path / "full.pt")
    again = NearNominalFDI.load(tmp_path / "full.pt")
    assert again.n_full == n_full and torch.equal(again.basis_, net.basis_)
    with pytest.raises(ValueError, match="reads records of 200 samples"):
        again.check_for(make_pipeline(), "the synthetic pipeline")


def test_its_held_out_r2_names_what_it_does_not_identify(fitted, tmp_path):
    fitted = copy.deepcopy(fitted)
    alpha, k = synthetic(500, 1)
    fitted.calibrate(0, alpha, k, k, torch.full((500,), 0.01, dtype=torch.float64))
    # the synthetic records do not see the phase: its estimate is the training prior
    assert fitted.not_identified(0.01) == ["eccentricity_phase"]
    # beyond the last calibrated level, that level's (this network was trained at 0.01 alone)
    names = ["dry_friction", "backlash", "short_a", "short_b", "short_c", "eccentricity", "eccentricity_phase"]
    last = [n for n, v in zip([*names, "gain_drift"], fitted.r2_[1].tolist()) if v < 0.25]
    assert fitted.not_identified(0.05) == last and "eccentricity_phase" in last
    with torch.no_grad():
        mse = (fitted(alpha, torch.full((500,), 0.01, dtype=torch.float64)) - k).pow(2).mean(0)
    torch.testing.assert_close(fitted.r2_[0], 1.0 - mse / k.var(0, unbiased=False), rtol=0, atol=1e-9)
    assert float(fitted.r2_[0, 6]) < 0.25 < float(fitted.r2_[0, [0, 1, 2, 3, 4, 5, 7]].min())
    # a file calibrated before R^2 was measured loads, and says it does not know
    fitted.save(tmp_path / "nn.pt")
    data = torch.load(tmp_path / "nn.pt", weights_only=True)
    data["state"] = {name: v for name, v in data["state"].items() if name != "r2_"}
    torch.save(data, tmp_path / "old.pt")
    old = NearNominalFDI.load(tmp_path / "old.pt")
    assert old.not_identified(0.01) is None
    torch.testing.assert_close(old.half_widths_, fitted.half_widths_)


def test_the_gate_reads_only_the_components_the_pipeline_identifies(fitted, tmp_path):
    # a pipeline whose test command does not identify the eccentricity reads its training prior there (0.45 on a store
    # sampled far from nominal): gated on every damage, no new actuator would reach the network
    net = copy.deepcopy(fitted)
    _, k = synthetic(6, 6)
    k_pipeline = k.clone()
    k_pipeline[:, 5] = 0.45  # the eccentricity's prior
    k_pipeline[1, 2] = 0.4  # a large short the pipeline does see
    noise = torch.full((6,), 0.01, dtype=torch.float64)
    assert not bool(net.gated(k_pipeline, noise).any())
    net.gate_on(["eccentricity", "eccentricity_phase", "gain_drift"])
    assert net.gated(k_pipeline, noise).tolist() == [True, False, True, True, True, True]
    assert net.gate_components_.tolist() == [True] * 5 + [False] * 3
    # kept in the file; a file from before it gates on every damage
    net.save(tmp_path / "nn.pt")
    assert torch.equal(NearNominalFDI.load(tmp_path / "nn.pt").gate_components_, net.gate_components_)
    data = torch.load(tmp_path / "nn.pt", weights_only=True)
    data["state"] = {name: v for name, v in data["state"].items() if name != "gate_components_"}
    torch.save(data, tmp_path / "old.pt")
    assert NearNominalFDI.load(tmp_path / "old.pt").gate_components_.tolist() == [True] * 6 + [False, True]
    with pytest.raises(ValueError, match="unknown fault names"):
        net.gate_on(["eccentricty"])
    with pytest.raises(ValueError, match="identifies no damage"):
        net.gate_on(list(FAULT_NAMES))
