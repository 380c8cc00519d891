"""Hidden strengths by detectability (phm_torch.workbench.detectability, the bench's ``--strength-mode snr``):
the scaled strength gives the requested signature SNR, measured independently, on a tiny LF record."""

from __future__ import annotations

import pytest
import torch

from phm_torch.command import Chirp
from phm_torch.params import load_actuator
from phm_torch.workbench import Case
from phm_torch.workbench.detectability import scale_to_snr, scaled, signature_snr

DURATION = 0.1  # [s]


@pytest.fixture(scope="module")
def setup():
    torch.set_num_threads(1)
    return load_actuator(), Chirp(duration=DURATION)


def test_scaled_strength_gives_the_requested_snr(setup):
    params, cmd = setup
    noise = {"current": 0.02, "position": 2e-5}
    cases = [
        Case({"viscous_friction": {"coefficient": 1e-5}}, noise),
        Case({"cogging_torque": {"amplitude": 1e-3, "phase": 0.7}}, noise),
        Case({}, noise),
    ]
    targets = [3.0, 0.5, None]
    out, info = scale_to_snr(params, cases, targets, cmd, DURATION)
    assert out[2] is cases[2] and info[2] == {}
    assert out[1].effects["cogging_torque"]["phase"] == 0.7  # shape parameters kept
    measured = signature_snr(params, out, cmd, DURATION)
    for i in (0, 1):
        assert measured[i] == pytest.approx(targets[i], rel=0.25)
        assert info[i]["snr"] == pytest.approx(measured[i], rel=1e-9)
        assert info[i]["factor"] == pytest.approx(targets[i] / info[i]["probe_snr"], rel=0.25)
    assert measured[2] == 0.0


def test_snr_is_in_noise_units(setup):
    """The same signature under twice the noise on both channels is half the SNR (noise-free simulations)."""
    params, cmd = setup
    eff = {"viscous_friction": {"coefficient": 3e-5}}
    a, b = signature_snr(
        params,
        [Case(eff, {"current": 0.02, "position": 2e-5}), Case(eff, {"current": 0.04, "position": 4e-5})],
        cmd,
        DURATION,
    )
    assert a > 0 and b == pytest.approx(a / 2, rel=1e-9)


def test_bad_input_names_the_field(setup):
    params, cmd = setup
    case = Case({"viscous_friction": {}}, {"current": 0.02})
    with pytest.raises(ValueError, match=r"case.noise\['position'\]"):
        signature_snr(params, [case], cmd, DURATION)
    with pytest.raises(ValueError, match="targets"):
        scale_to_snr(params, [case], [-1.0], cmd, DURATION)
    assert scaled(Case({"aero_hinge_load": {"stiffness": 10.0}}), 2.0).effects["aero_hinge_load"] == {
        "stiffness": 20.0,
        "bias": 2.0,
    }  # missing strength parameters scale from their defaults
