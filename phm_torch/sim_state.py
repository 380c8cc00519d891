"""The simulator's state (everything that evolves), batch first, and the selection of some of its rows.

A state is a value: ``EMASimulator.step`` returns a new one, and ``EMASimulator.run(..., state=...)`` continues a
simulation from the state an earlier run ended in (``Signals.state``). :meth:`SimState.rows` keeps some actuators
of the batch, so that only those a caller still needs (a frequency response that has not settled) go on.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any

import torch

from .physics.controller import ControlState
from .physics.mechanics import MechState
from .plant import Plant


def take_rows(value: Any, index: torch.Tensor | slice) -> Any:
    """``value`` with every batch-first tensor in it cut to the rows ``index``: a tensor (0-d ones, shared by the
    batch, kept), a dataclass, dict or tuple of them; anything else (a datasheet, a number) as it is."""
    if isinstance(value, torch.Tensor):
        return value if value.ndim == 0 else value[index]
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        changes = {f.name: take_rows(getattr(value, f.name), index) for f in dataclasses.fields(value) if f.init}
        return dataclasses.replace(value, **changes)
    if isinstance(value, dict):
        return {name: take_rows(v, index) for name, v in value.items()}
    if isinstance(value, tuple):
        return tuple(take_rows(v, index) for v in value)
    return value


@dataclass
class SimState:
    """Everything that evolves; tensors are batch-first."""

    plant: Plant
    mech: MechState
    ctrl: ControlState
    elec: torch.Tensor  # motor-model state: phase currents (B, 3) [A] or DC current (B,) [A]
    lvdt: torch.Tensor  # LVDT reading (B,) [rad]
    filt: tuple[torch.Tensor, torch.Tensor]  # Butterworth state (y [A], dy/dt [A/s]), each (B,)
    envelope: torch.Tensor  # unfiltered envelope at the last substep end (B,) [A]
    time: torch.Tensor | None = None  # 0-d, start of the next period [s]
    energy: dict[str, torch.Tensor] | None = None

    def rows(self, index: torch.Tensor | slice) -> SimState:
        """The state of the actuators ``index`` of the batch (a tensor of row numbers or a slice), at the same time."""
        return take_rows(self, index)


def at_rotor_angle(state: SimState, theta_m: float, gear_ratio: float) -> SimState:
    """``state`` (at rest) moved to the motor angle ``theta_m`` [rad]: the user side, gear and LVDT at
    theta_m / N, so the actuator rests there as it does at zero (no twist, no position error left to the loop
    if the command is offset by the same theta_m / N)."""
    th = torch.full_like(state.mech.theta_m, theta_m)
    mech = MechState(th, torch.zeros_like(th), th / gear_ratio, torch.zeros_like(th))
    return dataclasses.replace(state, mech=mech, lvdt=th / gear_ratio)
