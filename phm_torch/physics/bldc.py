"""High-fidelity motor: PWM three-phase inverter + BLDC with floating neutral (ema_reference.md §1, §3).

Per substep h (a fraction of the PWM period): Hall sector -> driven pair (high, low) and off phase;
centre-aligned PWM with both driven legs switching (high leg duty (1+d)/2, low leg (1-d)/2), whose
leg voltages are averaged exactly over the substep (volt-seconds are exact, the ripple is resolved at
h); the off phase conducts through its diodes until its current reaches zero, then floats. Phase
equations v_x - v_n = R_x i_x + L_x di_x/dt + e_x with sum(i) = 0 are integrated by backward Euler,
stable for every short-circuit level.
"""

from __future__ import annotations

import torch

from .commutation import emf_constants, hall_sector, phase_shapes, sector_masks


class BLDCMotor:
    """Switch-averaged-per-substep PWM inverter and trapezoidal BLDC motor; state = phase currents (B, 3) [A]."""

    fidelity = "hf"

    def __init__(self, substeps: int = 10):
        if substeps < 2:
            raise ValueError(f"hf.substeps must be >= 2 to resolve the PWM ripple, got {substeps}")
        self.substeps = substeps

    def init_state(self, plant) -> torch.Tensor:
        return plant.phase_resistance.new_zeros(plant.batch, 3)

    def feedback_current(self, currents: torch.Tensor, theta_m: torch.Tensor, plant) -> torch.Tensor:
        """I_fb = (i_high - i_low) / 2 of the driven pair [A] (B,)."""
        hi, lo, _ = sector_masks(hall_sector(plant.pole_pairs_f * theta_m), currents.dtype)
        return 0.5 * ((hi * currents).sum(-1) - (lo * currents).sum(-1))

    def step(self, currents: torch.Tensor, duty: torch.Tensor, t_in_period: float, theta_m: torch.Tensor,
             omega_m: torch.Tensor, emf_scale, plant, h: float, period: float
             ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, dict[str, torch.Tensor]]:
        """Advance the phase currents over [t_in_period, t_in_period + h] of the PWM period.

        Args:
            currents: phase currents (B, 3) [A].  duty: duty d in [-1, 1] (B,).
            theta_m, omega_m: motor angle [rad] and speed [rad/s] (B,).
            emf_scale: factor on the EMF constants (effects) [-], scalar or (B,).
        Returns:
            (new currents (B, 3) [A], torque (B,) [N m], envelope (|ia|+|ib|+|ic|)/2 (B,) [A],
            extras with ``power_in`` [W], the mean inverter output power over the substep).
        """
        theta_e = plant.pole_pairs_f * theta_m
        hi, lo, off = sector_masks(hall_sector(theta_e), currents.dtype)
        ke = emf_constants(theta_m, plant) * (torch.as_tensor(emf_scale).unsqueeze(-1)
                                              if torch.is_tensor(emf_scale) and emf_scale.ndim else emf_scale)
        kshape = ke * phase_shapes(theta_e)                      # (B, 3) [V s/rad]
        emf = kshape * omega_m.unsqueeze(-1)

        vdc = plant.supply_voltage
        t0, t1 = t_in_period, t_in_period + h
        mid = 0.5 * period

        def on_fraction(width: torch.Tensor) -> torch.Tensor:
            a, b = mid - 0.5 * width, mid + 0.5 * width
            return (torch.minimum(b, torch.full_like(b, t1)) - torch.maximum(a, torch.full_like(a, t0))
                    ).clamp(min=0.0) / h

        frac_hi = on_fraction(0.5 * (1.0 + duty) * period)
        frac_lo = on_fraction(0.5 * (1.0 - duty) * period)
        i_off = (off * currents).sum(-1)
        v_diode = torch.where(i_off < 0, vdc, torch.zeros_like(vdc))
        volts = (vdc * frac_hi).unsqueeze(-1) * hi + (vdc * frac_lo).unsqueeze(-1) * lo + v_diode.unsqueeze(-1) * off

        # Backward Euler with floating neutral, all three phases conducting.
        a = plant.inductance / h + plant.resistance                     # (B, 3)
        b = plant.inductance / h * currents + volts - emf
        v_n = (b / a).sum(-1) / (1.0 / a).sum(-1)
        i3 = (b - v_n.unsqueeze(-1)) / a
        # Off phase open (or its diode blocking this step): one loop through the driven pair,
        # starting from the pair's flux so that the clamp conserves it.
        pair = hi + lo
        l_pair = (plant.inductance * pair).sum(-1)
        flux = (plant.inductance * currents * (hi - lo)).sum(-1)
        drive = ((volts - emf) * (hi - lo)).sum(-1)
        i_loop = (flux / h + drive) / (l_pair / h + (plant.resistance * pair).sum(-1))
        i2 = i_loop.unsqueeze(-1) * (hi - lo)
        i3_off = (off * i3).sum(-1)
        conducting = (i_off != 0) & (torch.sign(i3_off) == torch.sign(i_off))
        new = torch.where(conducting.unsqueeze(-1), i3, i2)

        torque = (kshape * new).sum(-1)
        envelope = 0.5 * new.abs().sum(-1)
        power_in = (volts * new).sum(-1)  # the neutral potential drops out since sum(i) = 0
        return new, torque, envelope, {"power_in": power_in, "phase_currents": new}
