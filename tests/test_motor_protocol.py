"""The motor protocol (physics/motor.py) and the energy bookkeeping (physics/energy.py) against analytic values."""

from __future__ import annotations

import math

import pytest
import torch

from phm_torch.command import Chirp
from phm_torch.params import load_actuator
from phm_torch.physics.dc_motor import DCMotor
from phm_torch.physics.energy import ACCOUNTS, elastic_energy, stored_energy
from phm_torch.physics.mechanics import MechState, backlash_deflection, end_stop_penetration
from phm_torch.physics.motor import MOTORS, Motor
from phm_torch.plant import build_plant
from phm_torch.simulator import SHARED_CHANNELS, EMASimulator

P = load_actuator()
NOM = list(P.nominal_faults)


def plant(batch: int = 1):
    return build_plant(P, torch.tensor([NOM] * batch, dtype=torch.float64))


def mech(theta_m, omega_m, theta_u, omega_u) -> MechState:
    return MechState(*(torch.tensor([float(v)], dtype=torch.float64) for v in (theta_m, omega_m, theta_u, omega_u)))


@pytest.mark.parametrize("fidelity", sorted(MOTORS))
def test_every_motor_follows_the_protocol(fidelity):
    motor = MOTORS[fidelity]()
    assert isinstance(motor, Motor) and motor.fidelity == fidelity
    assert motor.substeps == motor.default_substeps
    pl = plant(2)
    elec = motor.init_state(pl)
    assert set(motor.sample(elec)) == set(motor.channels) and not set(motor.channels) & set(SHARED_CHANNELS)
    assert torch.equal(
        motor.magnetic_energy(elec, torch.zeros(2, dtype=torch.float64), pl), torch.zeros(2, dtype=torch.float64)
    )
    terms = motor.electrical_energy(elec, elec, torch.zeros(2), torch.zeros(2), pl, 1e-5)
    assert "copper" in terms and set(terms) <= set(ACCOUNTS)


def test_magnetic_energy_and_copper_loss_of_each_motor():
    pl, h = plant(), 1e-5
    theta_e = math.pi / 2  # mid-sector: phases a (high) and b (low) conduct, c is off
    theta_m = torch.tensor([theta_e / P.pole_pairs], dtype=torch.float64)
    i = torch.tensor([[3.0, -3.0, 0.0]], dtype=torch.float64)
    hf = MOTORS["hf"]()
    assert hf.magnetic_energy(i, theta_m, pl).item() == pytest.approx(P.phase_inductance * 9.0)  # 2 x L i^2 / 2
    assert hf.electrical_energy(i, i, theta_m, theta_m, pl, h)["copper"].item() == pytest.approx(
        2 * P.phase_resistance * 9 * h
    )
    lf, current = MOTORS["lf"](), torch.tensor([3.0], dtype=torch.float64)
    # the conducting pair in series: L_eq = 2 L, R_eq = 2 R; no angle change, no inductance exchange
    assert lf.magnetic_energy(current, theta_m, pl).item() == pytest.approx(P.phase_inductance * 9.0)
    terms = lf.electrical_energy(current, current, theta_m, theta_m, pl, h)
    assert terms["copper"].item() == pytest.approx(2 * P.phase_resistance * 9 * h) and terms["numerical"].item() == 0.0


def test_elastic_energy_uses_the_mechanics_play_and_end_stops():
    pl = plant()
    half, n = 0.5 * P.backlash, P.gear_ratio
    for delta, expected in ((3 * half, 2 * half), (-3 * half, -2 * half), (0.5 * half, 0.0)):
        m = mech(delta * n, 0, 0, 0)  # theta_u = 0: the gear deflection is theta_m / N
        assert backlash_deflection(m, pl).item() == pytest.approx(expected, abs=1e-18)
        assert elastic_energy(m, pl).item() == pytest.approx(0.5 * P.output_stiffness * expected**2, abs=1e-18)
    stop = P.end_stop_angle
    for theta_u, expected in ((stop + 1e-3, 1e-3), (-stop - 2e-3, -2e-3), (0.5 * stop, 0.0)):
        m = mech(theta_u * n, 0, theta_u, 0)  # no gear deflection
        assert end_stop_penetration(m, pl).item() == pytest.approx(expected, abs=1e-15)
        assert elastic_energy(m, pl).item() == pytest.approx(
            0.5 * P.end_stop_stiffness * expected**2, rel=1e-9, abs=1e-18
        )
    moving = mech(0, 100.0, 0, 0.5)
    kinetic = 0.5 * P.motor_inertia * 100.0**2 + 0.5 * P.user_inertia * 0.25
    assert stored_energy(MOTORS["lf"](), pl, moving, torch.zeros(1, dtype=torch.float64)).item() == pytest.approx(
        kinetic
    )


class _ProbedDC(DCMotor):
    """The LF motor with one channel of its own: the simulator takes a new fidelity with no change."""

    fidelity = "test_probed_dc"
    channels = ("i_dc",)

    def sample(self, current: torch.Tensor) -> dict[str, torch.Tensor]:
        return {"i_dc": current}


def test_a_new_motor_needs_no_simulator_change():
    MOTORS[_ProbedDC.fidelity] = _ProbedDC
    try:
        k = torch.tensor([NOM, [0.5, 0.3, 0.4, 0.0, 0.2, 0.5, 0.2, 0.7]], dtype=torch.float64)
        probed = EMASimulator(P, _ProbedDC.fidelity).run(k, Chirp(), 0.05, energy=True)
    finally:
        MOTORS.pop(_ProbedDC.fidelity)
    lf = EMASimulator(P, "lf").run(k, Chirp(), 0.05, energy=True)
    assert set(probed.channels) == set(lf.channels) | {"i_dc"}
    assert all(torch.equal(probed[c], lf[c]) for c in lf.channels)
    assert probed["i_dc"].abs().max() > 0.1  # the raw DC current [A]
    assert all(torch.equal(probed.energy[a], lf.energy[a]) for a in lf.energy)
