"""High-fidelity motor: PWM three-phase inverter + BLDC with floating neutral (ema_reference.md §1, §3).

Per substep h (a fraction of the PWM period): Hall sector -> driven pair (high, low) and off phase;
centre-aligned PWM with both driven legs switching (high leg duty (1+d)/2, low leg (1-d)/2), whose
leg voltages are averaged exactly over the substep (volt-seconds are exact, the ripple is resolved at
h); the off phase conducts through its diodes until its current reaches zero, then floats. Phase
equations v_x - v_n = R_x i_x + L_x di_x/dt + e_x with sum(i) = 0 are integrated by the trapezoidal
rule (A-stable for every short-circuit level, and energy-exact: the supply energy of a step equals the
copper loss, the change of magnetic energy and the electromechanical work at the mid-step current).

The three phases are kept as separate (B,) tensors: reductions over a trailing dimension of 3 cost
more than the arithmetic itself on CPU.
"""

from __future__ import annotations

import torch

from .commutation import eccentricity_factors, hall_sector, phase_shapes

# Sectors (see commutation.SECTOR_TABLE) in which phase x is high, low or off.
_HIGH = ((0, 1), (2, 3), (4, 5))
_LOW = ((3, 4), (0, 5), (1, 2))


def _member(sector: torch.Tensor, pair: tuple[int, int], dtype: torch.dtype) -> torch.Tensor:
    return ((sector == pair[0]) | (sector == pair[1])).to(dtype)


def phase_roles(theta_e: torch.Tensor) -> tuple[list[torch.Tensor], list[torch.Tensor]]:
    """Float masks (high[x], low[x]) per phase x for the Hall sector of theta_e (B,)."""
    s = hall_sector(theta_e)
    return (
        [_member(s, _HIGH[x], theta_e.dtype) for x in range(3)],
        [_member(s, _LOW[x], theta_e.dtype) for x in range(3)],
    )


def emf_shape_constants(theta_m: torch.Tensor, plant, emf_scale) -> list[torch.Tensor]:
    """k_e,x(theta_m) * trapezoid_x(theta_e) for x = a, b, c; each (B,) [V s/rad]."""
    ecc = eccentricity_factors(theta_m, plant.eccentricity, plant.ecc_phase)
    shapes = phase_shapes(plant.pole_pairs_f * theta_m)
    return [plant.emf[:, x] * ecc[x] * shapes[:, x] * emf_scale for x in range(3)]


class BLDCMotor:
    """PWM inverter and trapezoidal BLDC motor; state = phase currents (B, 3) [A] (see ``motor.Motor``)."""

    fidelity = "hf"
    default_substeps = 10  # 10 us at 10 kHz: resolves the PWM ripple
    # Ten unrolled substeps compile for minutes and run no faster than one compiled substep called ten times.
    compile_whole_period = False
    channels = ("ia", "ib", "ic")  # unfiltered phase currents [A]

    def __init__(self, substeps: int = default_substeps):
        if substeps < 2:
            raise ValueError(f"hf.substeps must be >= 2 to resolve the PWM ripple, got {substeps}")
        self.substeps = substeps

    def init_state(self, plant) -> torch.Tensor:
        return plant.phase_resistance.new_zeros(plant.batch, 3)

    def feedback_current(self, currents: torch.Tensor, theta_m: torch.Tensor, plant) -> torch.Tensor:
        """I_fb = (i_high - i_low) / 2 of the driven pair [A] (B,)."""
        high, low = phase_roles(plant.pole_pairs_f * theta_m)
        i = currents.unbind(-1)
        return 0.5 * sum((high[x] - low[x]) * i[x] for x in range(3))

    def sample(self, currents: torch.Tensor) -> dict[str, torch.Tensor]:
        """The phase currents ``ia``, ``ib``, ``ic`` [A], each (B,)."""
        return {"ia": currents[:, 0], "ib": currents[:, 1], "ic": currents[:, 2]}

    def magnetic_energy(self, currents: torch.Tensor, theta_m: torch.Tensor, plant) -> torch.Tensor:
        """sum_x L_x i_x^2 / 2 [J] (B,)."""
        return 0.5 * (plant.inductance * currents**2).sum(-1)

    def electrical_energy(
        self, old: torch.Tensor, new: torch.Tensor, theta_old: torch.Tensor, theta_new: torch.Tensor, plant, h: float
    ) -> dict[str, torch.Tensor]:
        """Copper loss sum_x R_x i_x^2 h [J] (B,) at the trapezoidal rule's mid-step currents; the phase
        inductances do not depend on the rotor angle, so the windings exchange nothing else."""
        i2 = (0.5 * (new + old)) ** 2
        return {"copper": h * (plant.resistance * i2).sum(-1)}

    def step(
        self,
        currents: torch.Tensor,
        duty: torch.Tensor,
        t_in_period: torch.Tensor,
        theta_m: torch.Tensor,
        omega_m: torch.Tensor,
        emf_scale,
        plant,
        h: float,
        period: float,
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, dict[str, torch.Tensor]]:
        """Advance the phase currents over [t_in_period, t_in_period + h] of the PWM period.

        Args:
            currents: phase currents (B, 3) [A].  duty: duty d in [-1, 1] (B,).
            t_in_period: start of the substep within the PWM period, 0-d tensor [s].
            theta_m, omega_m: motor angle [rad] and speed [rad/s] (B,).
            emf_scale: factor on the EMF constants (effects) [-], scalar or (B,).
        Returns:
            (new currents (B, 3) [A], mean torque over the substep (B,) [N m], envelope
            (|ia|+|ib|+|ic|)/2 at the substep end (B,) [A], extras with ``power_in`` [W], the mean
            inverter output power over the substep).
        """
        high, low = phase_roles(plant.pole_pairs_f * theta_m)
        kshape = emf_shape_constants(theta_m, plant, emf_scale)
        i = currents.unbind(-1)
        vdc = plant.supply_voltage
        t0, t1, mid = t_in_period, t_in_period + h, 0.5 * period
        # Exact overlap of the centred on-window [mid - w/2, mid + w/2] with the substep.
        half_hi = 0.25 * (1.0 + duty) * period
        half_lo = 0.25 * (1.0 - duty) * period
        frac_hi = (torch.minimum(mid + half_hi, t1) - torch.maximum(mid - half_hi, t0)).clamp(min=0.0) / h
        frac_lo = (torch.minimum(mid + half_lo, t1) - torch.maximum(mid - half_lo, t0)).clamp(min=0.0) / h
        v_hi, v_lo = vdc * frac_hi, vdc * frac_lo

        a, b, v, off, i_off = [], [], [], [], 0.0
        for x in range(3):
            o = 1.0 - high[x] - low[x]
            diode = torch.where(i[x] < 0, vdc, torch.zeros_like(vdc))  # off phase through its diodes
            vx = high[x] * v_hi + low[x] * v_lo + o * diode
            lh = plant.inductance[:, x] / h
            half_r = 0.5 * plant.resistance[:, x]
            a.append(lh + half_r)
            b.append((lh - half_r) * i[x] + vx - kshape[x] * omega_m)
            v.append(vx)
            off.append(o)
            i_off = i_off + o * i[x]
        # Trapezoidal rule, three phases conducting, neutral from sum(i) = 0.
        inv = [1.0 / a[x] for x in range(3)]
        v_n = (b[0] * inv[0] + b[1] * inv[1] + b[2] * inv[2]) / (inv[0] + inv[1] + inv[2])
        i3 = [(b[x] - v_n) * inv[x] for x in range(3)]
        # Off phase open, or its diode blocking within the step: a single loop through the pair,
        # started from the pair's flux so that the clamp conserves it.
        sgn = [high[x] - low[x] for x in range(3)]
        num = sgn[0] * b[0] + sgn[1] * b[1] + sgn[2] * b[2]  # b_high - b_low
        den = a[0] + a[1] + a[2] - (off[0] * a[0] + off[1] * a[1] + off[2] * a[2])
        i_loop = num / den
        i3_off = off[0] * i3[0] + off[1] * i3[1] + off[2] * i3[2]
        conducting = (i_off != 0) & (torch.sign(i3_off) == torch.sign(i_off))
        new = [torch.where(conducting, i3[x], sgn[x] * i_loop) for x in range(3)]

        mid_i = [0.5 * (i[x] + new[x]) for x in range(3)]
        torque = kshape[0] * mid_i[0] + kshape[1] * mid_i[1] + kshape[2] * mid_i[2]
        envelope = 0.5 * (new[0].abs() + new[1].abs() + new[2].abs())
        power_in = v[0] * mid_i[0] + v[1] * mid_i[1] + v[2] * mid_i[2]  # neutral drops out: sum(i) = 0
        return torch.stack(new, dim=-1), torque, envelope, {"power_in": power_in}
