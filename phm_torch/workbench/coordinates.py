"""The calibrated model's physical coordinates per record: where the workbench maps and orders its residuals."""

from __future__ import annotations

import numpy as np

from ..plant import build_plant
from .calibrate import Calibration
from .diagnostics import Coordinates


def coordinates(cal: Calibration) -> list[Coordinates]:
    """Motor speed, angle and torque sign of the calibrated model and the measured current, per record.

    The motor torque is rebuilt from the model's states with its calibrated parameters:
    J_m dω/dt + c_m ω + T_c sign(ω) + K_t (θ_m / N - θ_u) / N (backlash and output damping neglected: only
    its sign is used).
    """
    k, scales, _, _ = cal.space.settings(cal.x.reshape(1, -1))
    plant = build_plant(cal.space.params, k, scales)
    jm, cm, tc = (float(getattr(plant, f)[0]) for f in ("motor_inertia", "motor_viscous", "coulomb_friction"))
    kt, n = float(plant.output_stiffness[0]), float(plant.gear_ratio[0])
    out = []
    for s, rec in zip(cal.simulated, cal.evaluator.records, strict=True):
        w, th, thu = (s[c].numpy() for c in ("speed", "motor_angle", "user_angle"))
        torque = jm * np.gradient(w) * rec.sample_rate + cm * w + tc * np.sign(w) + kt * (th / n - thu) / n
        out.append(
            Coordinates(w, th, rec.measured.get("current", s["current"]).numpy(), np.where(torque >= 0, 1.0, -1.0))
        )
    return out
