"""Discrete cascade controller: position P -> speed PI -> current PI -> duty, at the PWM rate.

Inputs are sampled at the PWM period boundary; the duty computed there is applied from the next
period (one period of computation delay). Forward-Euler integrators with conditional-integration
anti-windup (the integrator holds while the output is saturated and the error pushes further).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch


@dataclass
class ControlState:
    """Integrator states (B,): speed-loop integral [A], current-loop integral [V]; pending duty [-]."""

    speed_int: torch.Tensor
    current_int: torch.Tensor
    duty: torch.Tensor

    @classmethod
    def zeros(cls, batch: int, dtype: torch.dtype, device: torch.device) -> ControlState:
        return cls(*(torch.zeros(batch, dtype=dtype, device=device) for _ in range(3)))


def _pi(error: torch.Tensor, integral: torch.Tensor, kp, ki, limit, period: float) -> tuple[torch.Tensor, torch.Tensor]:
    raw = kp * error + integral
    out = torch.maximum(torch.minimum(raw, limit), -limit)
    winding = ((raw > limit) & (error > 0)) | ((raw < -limit) & (error < 0))
    integral = torch.where(winding, integral, integral + ki * period * error)
    return out, integral


def controller_step(
    state: ControlState,
    command: torch.Tensor,
    position: torch.Tensor,
    speed: torch.Tensor,
    current: torch.Tensor,
    plant,
    period: float,
) -> tuple[ControlState, dict[str, torch.Tensor]]:
    """One control period.

    Args:
        command: user-side position command [rad] (B,).  position: LVDT reading [rad] (B,).
        speed: motor speed [rad/s] (B,).  current: current feedback [A] (B,).
        period: control period [s].
    Returns:
        New state (whose ``duty`` is applied from the next period) and the references
        ``speed_ref`` [rad/s], ``current_ref`` [A], ``voltage`` [V].
    """
    speed_ref = plant.position_gain * (command - position)
    speed_ref = torch.maximum(torch.minimum(speed_ref, plant.speed_limit), -plant.speed_limit)
    current_ref, s_int = _pi(
        speed_ref - speed, state.speed_int, plant.speed_gain, plant.speed_integral_gain, plant.current_limit, period
    )
    voltage, c_int = _pi(
        current_ref - current,
        state.current_int,
        plant.current_gain,
        plant.current_integral_gain,
        plant.supply_voltage,
        period,
    )
    new = ControlState(s_int, c_int, voltage / plant.supply_voltage)
    return new, {"speed_ref": speed_ref, "current_ref": current_ref, "voltage": voltage}
