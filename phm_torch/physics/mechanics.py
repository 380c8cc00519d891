"""Drive-train mechanics shared by every fidelity.

Motor inertia with viscous and Karnopp stick-slip dry friction, gearbox (ratio N, ideal), backlash
dead zone in series with the output-stage stiffness/damping, user inertia with viscous damping and
unilateral spring-damper end stops. Semi-implicit Euler at the substep h; the stiffest mode (end-stop
contact, ~2200 rad/s) needs h << 1 ms, satisfied by every fidelity's substep.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch


@dataclass
class MechState:
    """Mechanical state, every tensor (B,): motor angle [rad] and speed [rad/s], user angle [rad] and
    speed [rad/s]. ``omega_m == 0`` exactly means the motor is stuck (Karnopp)."""

    theta_m: torch.Tensor
    omega_m: torch.Tensor
    theta_u: torch.Tensor
    omega_u: torch.Tensor

    @classmethod
    def zeros(cls, batch: int, dtype: torch.dtype, device: torch.device) -> MechState:
        # distinct tensors: aliased state fields confuse torch.compile's guards
        return cls(*(torch.zeros(batch, dtype=dtype, device=device) for _ in range(4)))


def backlash_deflection(state: MechState, plant) -> torch.Tensor:
    """Deflection of the output-stage spring past the play [rad] (B,), signed.

    Gear deflection delta = theta_m / N - theta_u; the play is ``plant.backlash`` (total, user side), so the
    spring is compressed by delta - b/2 in forward contact, delta + b/2 in reverse contact, and not at all
    inside the play.
    """
    delta = state.theta_m / plant.gear_ratio - state.theta_u
    half = 0.5 * plant.backlash
    zero = torch.zeros_like(delta)
    return torch.where(delta > half, delta - half, torch.where(delta < -half, delta + half, zero))


def transmission_torque(state: MechState, plant) -> torch.Tensor:
    """Torque the output stage transmits to the user [N m] (B,), through the backlash dead zone.

    In contact the spring-damper acts; the damper may not pull the teeth together (torque clipped).
    """
    x = backlash_deflection(state, plant)
    rate = state.omega_m / plant.gear_ratio - state.omega_u
    torque = plant.output_stiffness * x + plant.output_damping * rate
    zero = torch.zeros_like(x)
    return torch.where(x > 0, torque.clamp(min=0.0), torch.where(x < 0, torque.clamp(max=0.0), zero))


def end_stop_penetration(state: MechState, plant) -> torch.Tensor:
    """How far the user angle is past an end stop [rad] (B,), signed: theta_u - theta_stop beyond the upper
    stop, theta_u + theta_stop beyond the lower one, 0 between them."""
    over = state.theta_u - plant.end_stop_angle
    under = state.theta_u + plant.end_stop_angle
    zero = torch.zeros_like(over)
    return torch.where(over > 0, over, torch.where(under < 0, under, zero))


def end_stop_torque(state: MechState, plant) -> torch.Tensor:
    """Reaction of the end stops on the user side [N m] (B,), opposing penetration (the damper may not pull)."""
    x = end_stop_penetration(state, plant)
    force = plant.end_stop_stiffness * x + plant.end_stop_damping * state.omega_u
    zero = torch.zeros_like(x)
    return torch.where(x > 0, force.clamp(min=0.0), torch.where(x < 0, force.clamp(max=0.0), zero))


def mechanics_step(
    state: MechState,
    motor_torque: torch.Tensor,
    load_torque: torch.Tensor,
    kinetic_friction: torch.Tensor,
    breakaway: torch.Tensor,
    plant,
    h: float,
) -> tuple[MechState, dict[str, torch.Tensor]]:
    """Advance the drive train by h seconds.

    Args:
        motor_torque: electromagnetic plus effect torque on the motor shaft [N m] (B,).
        load_torque: external user-side torque opposing positive motion [N m] (B,).
        kinetic_friction: sliding dry-friction magnitude [N m] (B,), applied against the motion.
        breakaway: static friction [N m] (B,) that holds a stuck motor.
        h: step [s].
    Returns:
        The new state and the torques of the step (``transmission``, ``friction``, ``end_stop``) [N m],
        used by energy-balance checks.
    """
    t_tr = transmission_torque(state, plant)
    t_stop = end_stop_torque(state, plant)
    n, jm = plant.gear_ratio, plant.motor_inertia

    drive = motor_torque - plant.motor_viscous * state.omega_m - t_tr / n
    w = state.omega_m
    moving = w != 0
    sgn = torch.sign(w)
    w_slide = w + h * (drive - kinetic_friction * sgn) / jm
    crossed = moving & (torch.sign(w_slide) != sgn)
    holds = drive.abs() <= breakaway
    # Stuck (or stopping this step) and the drive cannot break away: stay at rest (Karnopp).
    stick = (~moving | crossed) & holds
    w_break = h * (drive - kinetic_friction * torch.sign(drive)) / jm
    w_new = torch.where(stick, torch.zeros_like(w), torch.where(moving, w_slide, w_break))
    friction = torch.where(stick, drive, kinetic_friction * torch.where(moving, sgn, torch.sign(drive)))

    acc_u = (t_tr - plant.user_damping * state.omega_u - t_stop - load_torque) / plant.user_inertia
    wu_new = state.omega_u + h * acc_u
    new = MechState(state.theta_m + h * w_new, w_new, state.theta_u + h * wu_new, wu_new)
    return new, {"transmission": t_tr, "friction": friction, "end_stop": t_stop}
