"""The one eccentricity term (phm_torch/physics/commutation.py), used by the HF and the LF motor."""

from __future__ import annotations

import math

import torch

from phm_torch.physics.commutation import PHASE_OFFSETS, eccentricity_factors


def test_factors_are_one_plus_eps_cos_and_cancel_over_the_three_phases():
    theta = torch.linspace(0.0, 4 * math.pi, 1001, dtype=torch.float64)
    eps = torch.full_like(theta, 0.3)
    phi = torch.full_like(theta, 0.7)
    f = eccentricity_factors(theta, eps, phi)
    for x, alpha in enumerate(PHASE_OFFSETS):
        assert torch.allclose(f[x], 1.0 + 0.3 * torch.cos(theta - 0.7 - alpha), atol=1e-14, rtol=0.0)
    # balanced three-phase modulation: the mean EMF constant does not move with the rotor angle
    assert torch.allclose(sum(f), torch.full_like(theta, 3.0), atol=1e-14, rtol=0.0)
    # phase a's largest modulation, 1 + eps, where the rotor angle equals phi
    one = torch.ones(1, dtype=torch.float64)
    at_phi = eccentricity_factors(0.7 * one, 0.3 * one, 0.7 * one)
    assert at_phi[0].item() == 1.3 and max(v.item() for v in at_phi[1:]) < 1.0
    zero = eccentricity_factors(theta, torch.zeros_like(theta), phi)
    assert all(bool((v == 1.0).all()) for v in zero)  # no eccentricity: no modulation
