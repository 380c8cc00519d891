"""Low-fidelity motor: first-order DC equivalent with shape functions (seed paper, LF model).

R_eq I + L_eq dI/dt = V - k_eq omega_m,  T = k_eq I,  envelope = |I|.

The inverter is replaced by its period average V = d V_dc and the three phases by the conducting
pair. Short circuits and eccentricity enter through shape functions of the rotor angle: each phase x
carries a weight w_x(theta_e) in [0, 1] (1 while it conducts, blended over ``commutation_width``
around the Hall edges, sum of weights 2), and

  k_eq = sum_x w_x k_e (1 - a_k s_x)(1 + eps cos(theta_m - phi - alpha_x)),
  R_eq = sum_x w_x R (1 - a_R s_x),    L_eq = sum_x w_x L (1 - s_x) ** a_L,

with a_k, a_R, a_L and the width fitted to the HF model (``phm-fit-lf``, ``phm_torch/lf_fit.py``; values in
``conf/actuator/*.yaml: lf_shape``).
"""

from __future__ import annotations

import math

import torch

from .commutation import PHASE_OFFSETS, eccentricity_factors


def conduction_weights(theta_e: torch.Tensor, width: torch.Tensor) -> torch.Tensor:
    """Shape functions w_x(theta_e) (B,) -> (B, 3): smoothed indicator that phase x is driven.

    Phase A is driven (high or low) for theta_e in [30°, 150°] and [210°, 330°], i.e. while its
    trapezoid is flat; a raised-cosine blend of total width ``width`` [rad] smooths the edges.
    """
    x = theta_e.unsqueeze(-1) - theta_e.new_tensor(PHASE_OFFSETS)
    # distance to the nearest transition centre (0° or 180°, mod 180°), in [0, 90°]
    d = torch.remainder(x, math.pi)
    d = torch.minimum(d, math.pi - d)
    edge = math.pi / 6
    w = width.unsqueeze(-1)
    u = ((d - (edge - 0.5 * w)) / w.clamp(min=1e-9)).clamp(0.0, 1.0)  # width 0 -> a step at the edge
    return 0.5 - 0.5 * torch.cos(math.pi * u)


class DCMotor:
    """DC-equivalent motor; state = equivalent current (B,) [A] (see ``motor.Motor``)."""

    fidelity = "lf"
    default_substeps = 2  # 50 us at 10 kHz
    # A whole compiled period removes the per-call overhead that dominates this model's few operations.
    compile_whole_period = True
    channels: tuple[str, ...] = ()  # the shared channels only

    def __init__(self, substeps: int = default_substeps):
        if substeps < 1:
            raise ValueError(f"lf.substeps must be >= 1, got {substeps}")
        self.substeps = substeps

    def init_state(self, plant) -> torch.Tensor:
        return plant.phase_resistance.new_zeros(plant.batch)

    def feedback_current(self, current: torch.Tensor, theta_m: torch.Tensor, plant) -> torch.Tensor:
        return current

    def equivalent(self, theta_m: torch.Tensor, plant) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """(k_eq [V s/rad], R_eq [ohm], L_eq [H]) at motor angle theta_m, each (B,)."""
        w = conduction_weights(plant.pole_pairs_f * theta_m, plant.lf_commutation_width).unbind(-1)
        ecc = eccentricity_factors(theta_m, plant.eccentricity, plant.ecc_phase)
        k_eq = r_eq = l_eq = 0.0
        for x in range(3):  # phases unrolled: reductions over a trailing 3 are slow on CPU
            s = plant.short[:, x]
            k_eq = k_eq + w[x] * (1.0 - plant.lf_emf_short_gain * s) * ecc[x]
            r_eq = r_eq + w[x] * (1.0 - plant.lf_resistance_short_gain * s)
            l_eq = l_eq + w[x] * (1.0 - s) ** plant.lf_inductance_short_exponent
        return (k_eq * plant.back_emf_constant, r_eq * plant.phase_resistance, l_eq * plant.phase_inductance)

    def sample(self, current: torch.Tensor) -> dict[str, torch.Tensor]:
        """No channel of its own."""
        return {}

    def magnetic_energy(self, current: torch.Tensor, theta_m: torch.Tensor, plant) -> torch.Tensor:
        """L_eq(theta_m) I^2 / 2 [J] (B,)."""
        return 0.5 * self.equivalent(theta_m, plant)[2] * current**2

    def electrical_energy(
        self, old: torch.Tensor, new: torch.Tensor, theta_old: torch.Tensor, theta_new: torch.Tensor, plant, h: float
    ) -> dict[str, torch.Tensor]:
        """Copper loss R_eq I^2 h at the mid-step current and, as ``numerical``, the energy 0.5 (L_new - L_old) I^2
        [J] (B,) the shape functions exchange as L_eq changes with the rotor angle (not otherwise accounted)."""
        _, r, ind = self.equivalent(theta_old, plant)
        i2 = (0.5 * (new + old)) ** 2
        return {"numerical": 0.5 * (self.equivalent(theta_new, plant)[2] - ind) * new * new, "copper": h * r * i2}

    def step(
        self,
        current: torch.Tensor,
        duty: torch.Tensor,
        t_in_period: torch.Tensor,
        theta_m: torch.Tensor,
        omega_m: torch.Tensor,
        emf_scale,
        plant,
        h: float,
        period: float,
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, dict[str, torch.Tensor]]:
        """Trapezoidal-rule step of the DC equivalent; same signature as ``BLDCMotor.step``."""
        k_eq, r_eq, l_eq = self.equivalent(theta_m, plant)
        k_eq = k_eq * emf_scale
        volts = duty * plant.supply_voltage
        lh = l_eq / h
        new = ((lh - 0.5 * r_eq) * current + volts - k_eq * omega_m) / (lh + 0.5 * r_eq)
        mid = 0.5 * (current + new)
        return new, k_eq * mid, new.abs(), {"power_in": volts * mid}
