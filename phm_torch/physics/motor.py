"""The motor protocol: all a fidelity is to the simulator, and the registry of fidelities.

A fidelity is only its motor model; control, mechanics, sensors, faults, effects and the energy balance
are shared code (``simulator.py``, :mod:`.energy`) that asks the motor, through this protocol, for what
differs: its electrical state, its own acquisition channels, its magnetic energy and electrical losses, its
default substep and what one compiled graph covers.
"""

from __future__ import annotations

import math
from typing import ClassVar, Protocol, runtime_checkable

import torch

from .bldc import BLDCMotor
from .dc_motor import DCMotor


@runtime_checkable
class Motor(Protocol):
    """One motor model (one fidelity). ``elec`` is its electrical state, batch first.

    Attributes:
        fidelity: registry name (``"hf"``, ``"lf"``).
        default_substeps: substeps per PWM period when the caller gives none.
        compile_whole_period: ``torch.compile`` fuses a whole control period (controller + substeps) rather
            than one substep.
        channels: acquisition channels the motor adds to the shared ones (e.g. phase currents).
        substeps: substeps per PWM period of this instance.
    """

    fidelity: ClassVar[str]
    default_substeps: ClassVar[int]
    compile_whole_period: ClassVar[bool]
    channels: ClassVar[tuple[str, ...]]
    substeps: int

    def init_state(self, plant) -> torch.Tensor:
        """Electrical state at rest (zero currents)."""
        ...

    def feedback_current(self, elec: torch.Tensor, theta_m: torch.Tensor, plant) -> torch.Tensor:
        """Current the current loop and the effects see [A] (B,)."""
        ...

    def step(
        self,
        elec: torch.Tensor,
        duty: torch.Tensor,
        t_in_period: torch.Tensor,
        theta_m: torch.Tensor,
        omega_m: torch.Tensor,
        emf_scale,
        plant,
        h: float,
        period: float,
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, dict[str, torch.Tensor]]:
        """One substep: (new state, mean torque [N m] (B,), current envelope [A] (B,), ``{"power_in": [W]}``)."""
        ...

    def sample(self, elec: torch.Tensor) -> dict[str, torch.Tensor]:
        """The motor's own channels (those of ``channels``) at a state, each (B,)."""
        ...

    def magnetic_energy(self, elec: torch.Tensor, theta_m: torch.Tensor, plant) -> torch.Tensor:
        """Energy stored in the windings' inductance [J] (B,)."""
        ...

    def electrical_energy(
        self,
        elec_old: torch.Tensor,
        elec: torch.Tensor,
        theta_old: torch.Tensor,
        theta_new: torch.Tensor,
        plant,
        h: float,
    ) -> dict[str, torch.Tensor]:
        """Energy [J] (B,) of the motor's electrical accounts over one substep of h [s] (``copper``, and any
        other of :data:`.energy.ACCOUNTS`), from the states at its start and end."""
        ...


MOTORS: dict[str, type[Motor]] = {cls.fidelity: cls for cls in (BLDCMotor, DCMotor)}


def default_substeps(motor: type[Motor], pwm_frequency: float, sample_rate: float) -> int:
    """Substeps per PWM period when the caller gives none: the fidelity's default, raised to a multiple of the
    acquisition samples per period (sample_rate / pwm_frequency, when it is a whole number above 1) so that
    every sample falls on a substep boundary (a 40 kHz acquisition of a 10 kHz HF drive: 20, not 10)."""
    per_period = sample_rate / pwm_frequency
    whole = round(per_period)
    if whole > 1 and abs(per_period - whole) < 1e-9:
        return math.lcm(motor.default_substeps, whole)
    return motor.default_substeps
