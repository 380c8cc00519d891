"""The one NRMSE (phm_torch/metrics.py) and the sensor noise of simulated measurements
(phm_torch/sensor_noise.py): analytic values, the constant-reference case, the noise's std and independence."""

from __future__ import annotations

import math

import pytest
import torch

from phm_torch.metrics import nrmse
from phm_torch.sensor_noise import add_sensor_noise


def test_nrmse_of_an_offset_sine_is_the_offset_over_the_peak_to_peak():
    t = torch.linspace(0.0, 1.0, 10001, dtype=torch.float64)
    ref = 3.0 * torch.sin(2 * math.pi * 5 * t)  # range 6
    out = nrmse(torch.stack([ref + 0.06, ref, 1.1 * ref]), ref)  # batched over the leading axis
    assert out[0].item() == pytest.approx(0.01, rel=1e-9)  # RMS 0.06 / 6
    assert out[1].item() == 0.0
    assert out[2].item() == pytest.approx(0.1 * 3 / math.sqrt(2) / 6, rel=1e-3)  # RMS of 0.3 sin / 6


def test_nrmse_against_a_constant_reference_is_undefined_not_huge():
    ref = torch.full((2, 100), 2.0, dtype=torch.float64)
    out = nrmse(torch.stack([ref[0] + 1.0, ref[1]]), ref)
    assert torch.isnan(out).all()  # also when the signal matches exactly
    mixed = nrmse(torch.ones(2, 3), torch.tensor([[0.0, 1.0, 2.0], [5.0, 5.0, 5.0]]))
    assert mixed[0].item() == pytest.approx(math.sqrt(2 / 3) / 2) and math.isnan(mixed[1].item())


def test_sensor_noise_has_the_requested_std_and_each_channel_depends_only_on_the_seed():
    zeros = {c: torch.zeros(4, 50000, dtype=torch.float64) for c in ("current", "position", "speed")}
    noisy = add_sensor_noise(zeros, {"current": 0.02, "position": 3e-5}, seed=5)
    assert noisy["current"].std().item() == pytest.approx(0.02, rel=0.01)
    assert noisy["position"].std().item() == pytest.approx(3e-5, rel=0.01)
    assert noisy["speed"] is zeros["speed"] and zeros["current"].abs().max() == 0  # input left untouched
    only_position = add_sensor_noise(zeros, {"position": 3e-5}, seed=5)
    assert torch.equal(only_position["position"], noisy["position"]) and only_position["current"].abs().max() == 0
    assert not torch.equal(add_sensor_noise(zeros, {"current": 0.02}, seed=6)["current"], noisy["current"])
