"""Energy bookkeeping of a simulation: the stored energy of a state and the terms of the power balance.

Supply energy = copper + friction + viscous + damping + end-stop + load + stored (+ the LF motor's
inductance exchange, ``numerical``), each integrated per substep with the step's own discretisation so that
the balance closes to the integrators' accuracy (tests/test_physics.py::test_power_balance). The drive
train's geometry (play, end stops) is that of :mod:`.mechanics`; each motor declares its own electrical
terms (:class:`~.motor.Motor`).
"""

from __future__ import annotations

import torch

from .mechanics import MechState, backlash_deflection, end_stop_penetration
from .motor import Motor

# The accounts of the power balance [J], each (B,).
ACCOUNTS = ("input", "copper", "friction", "viscous", "damping", "end_stop", "load", "effect_work", "numerical")


def empty_accounts(batch: int, dtype: torch.dtype, device: torch.device) -> dict[str, torch.Tensor]:
    """Every account of :data:`ACCOUNTS` at zero, (B,) [J]."""
    return {key: torch.zeros(batch, dtype=dtype, device=device) for key in ACCOUNTS}


def elastic_energy(mech: MechState, plant) -> torch.Tensor:
    """Energy in the output-stage spring past the play and in the end stops [J] (B,)."""
    twist, over = backlash_deflection(mech, plant), end_stop_penetration(mech, plant)
    return 0.5 * plant.output_stiffness * twist**2 + 0.5 * plant.end_stop_stiffness * over**2


def stored_energy(motor: Motor, plant, mech: MechState, elec: torch.Tensor) -> torch.Tensor:
    """Kinetic + magnetic + elastic energy [J] (B,) of a state (zero at rest)."""
    kinetic = 0.5 * plant.motor_inertia * mech.omega_m**2 + 0.5 * plant.user_inertia * mech.omega_u**2
    return kinetic + motor.magnetic_energy(elec, mech.theta_m, plant) + elastic_energy(mech, plant)


def accumulate(
    acc: dict[str, torch.Tensor],
    motor: Motor,
    h: float,
    power_in: torch.Tensor,
    elec_old: torch.Tensor,
    elec: torch.Tensor,
    old: MechState,
    new: MechState,
    torques: dict[str, torch.Tensor],
    eff_motor: torch.Tensor | float,
    load: torch.Tensor,
    plant,
) -> None:
    """Add one substep's energies [J] to the accounts, in place.

    Args:
        h: substep [s].  power_in: mean inverter output power over the substep [W] (B,).
        elec_old, elec: motor state at the substep's start and end.  old, new: mechanical states likewise.
        torques: the mechanics step's ``transmission``, ``friction`` and ``end_stop`` torques [N m] (B,).
        eff_motor: effects' motor-shaft torque [N m].  load: user-side load torque [N m] (B,).
    """
    n = plant.gear_ratio
    for key, value in motor.electrical_energy(elec_old, elec, old.theta_m, new.theta_m, plant, h).items():
        acc[key] += value
    acc["input"] += h * power_in
    acc["friction"] += h * torques["friction"] * new.omega_m
    acc["viscous"] += h * plant.motor_viscous * old.omega_m * new.omega_m
    rate_new = new.omega_m / n - new.omega_u
    contact = torques["transmission"] != 0
    acc["damping"] += h * torch.where(
        contact, plant.output_damping * (old.omega_m / n - old.omega_u) * rate_new, torch.zeros_like(rate_new)
    )
    acc["damping"] += h * plant.user_damping * old.omega_u * new.omega_u
    acc["end_stop"] += h * torques["end_stop"] * new.omega_u
    acc["load"] += h * load * new.omega_u
    acc["effect_work"] += h * eff_motor * new.omega_m if torch.is_tensor(eff_motor) else 0.0
