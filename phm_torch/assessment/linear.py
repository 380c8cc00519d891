"""Linearised sampled-data model of the EMA position loop (the reference check of the assessment).

The LF actuator at its nominal fault vector, with the dry friction and the backlash removed (they have
no linearisation at rest), is a linear time-invariant plant: DC-equivalent motor, motor inertia with
viscous friction, output-stage spring-damper, user inertia, LVDT lag. It is discretised exactly with a
zero-order hold at the control period and closed with the discrete cascade controller of
``physics/controller.py`` (forward-Euler PI integrators, one period of computation delay). The loop is
opened at the position error: L(z) = theta_lvdt / e with speed_ref = K_pos * e.

All frequencies are in Hz, gains are ratios (not dB) unless a name says ``_db``, phases in degrees.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import scipy.linalg
import scipy.signal

from ..params import ActuatorParams


@dataclass(frozen=True)
class LinearLoop:
    """Discrete state-space (A, B, C, D) of the open position loop at the control period ``dt`` [s].

    Input: position error e [rad]; output: LVDT reading [rad]. ``closed`` is the closed loop
    command -> LVDT reading.
    """

    open: scipy.signal.StateSpace
    closed: scipy.signal.StateSpace
    dt: float

    def response(self, freqs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Open-loop L and closed-loop T (complex, same shape as ``freqs`` [Hz])."""
        freqs = np.asarray(freqs, dtype=float)
        z = np.exp(2j * math.pi * freqs.ravel() * self.dt)
        out = []
        for ss in (self.open, self.closed):
            eye = np.eye(ss.A.shape[0])
            h = [(ss.C @ np.linalg.solve(zi * eye - ss.A, ss.B))[0, 0] + ss.D[0, 0] for zi in z]
            out.append(np.asarray(h).reshape(freqs.shape))
        return out[0], out[1]


def linear_loop(params: ActuatorParams, position_gain_scale: float = 1.0) -> LinearLoop:
    """Build the linearised sampled-data position loop of ``params`` (LF motor, nominal faults).

    Args:
        params: the actuator datasheet.
        position_gain_scale: multiplier on K_pos (the k8 gain drift: 0.5 + k8).
    """
    p = params
    dt = p.control_period
    n = p.gear_ratio
    # DC equivalent of the conducting pair (physics/dc_motor.py with no fault: weights sum to 2).
    k_eq, r_eq, l_eq = 2.0 * p.back_emf_constant, 2.0 * p.phase_resistance, 2.0 * p.phase_inductance
    kt, ct = p.output_stiffness, p.output_damping
    # x = [I, theta_m, omega_m, theta_u, omega_u, lvdt]; input V [V].
    a = np.zeros((6, 6))
    a[0, 0], a[0, 2] = -r_eq / l_eq, -k_eq / l_eq
    a[1, 2] = 1.0
    a[2, 0] = k_eq / p.motor_inertia
    a[2, 1] = -kt / n**2 / p.motor_inertia
    a[2, 2] = -(p.motor_viscous + ct / n**2) / p.motor_inertia
    a[2, 3] = kt / n / p.motor_inertia
    a[2, 4] = ct / n / p.motor_inertia
    a[3, 4] = 1.0
    a[4, 1] = kt / n / p.user_inertia
    a[4, 2] = ct / n / p.user_inertia
    a[4, 3] = -kt / p.user_inertia
    a[4, 4] = -(ct + p.user_damping) / p.user_inertia
    if p.lvdt_time_constant > 0:
        a[5, 3], a[5, 5] = 1.0 / p.lvdt_time_constant, -1.0 / p.lvdt_time_constant
        sensor = 5
    else:  # an ideal sensor (the datasheet's 0): the loop reads theta_u itself; state 5 decays unused
        a[5, 5] = -1.0 / dt
        sensor = 3
    b = np.zeros((6, 1))
    b[0, 0] = 1.0 / l_eq
    m = np.zeros((7, 7))
    m[:6, :6], m[:6, 6:] = a * dt, b * dt
    e = scipy.linalg.expm(m)
    ad, bd = e[:6, :6], e[:6, 6]
    # Discrete states z = [x (6), speed_int, current_int, v_pending]; input u = position error.
    kpos = p.position_gain * position_gain_scale
    kw, kwi, kc, kci = p.speed_gain, p.speed_integral_gain, p.current_gain, p.current_integral_gain
    # speed_ref = kpos u;  current_ref = kw (speed_ref - omega) + s_int;  V = kc (current_ref - I) + c_int
    # (linear rows of the controller: d(quantity)/d(z) and d(quantity)/d(u))
    sref_z, sref_u = np.zeros(9), kpos
    cref_z = kw * (sref_z - _unit(9, 2))
    cref_z[6] += 1.0
    cref_u = kw * sref_u
    v_z = kc * (cref_z - _unit(9, 0))
    v_z[7] += 1.0
    v_u = kc * cref_u
    big_a = np.zeros((9, 9))
    big_b = np.zeros((9, 1))
    big_a[:6, :6] = ad
    big_a[:6, 8] = bd  # the pending voltage acts during this period
    big_a[6] = _unit(9, 6) + kwi * dt * (sref_z - _unit(9, 2))
    big_b[6, 0] = kwi * dt * sref_u
    big_a[7] = _unit(9, 7) + kci * dt * (cref_z - _unit(9, 0))
    big_b[7, 0] = kci * dt * cref_u
    big_a[8] = v_z  # computed now, applied from the next period
    big_b[8, 0] = v_u
    c = _unit(9, sensor)[None, :]
    d = np.zeros((1, 1))
    open_ss = scipy.signal.StateSpace(big_a, big_b, c, d, dt=dt)
    closed_ss = scipy.signal.StateSpace(big_a - big_b @ c, big_b, c, d, dt=dt)  # u = r - y
    return LinearLoop(open_ss, closed_ss, dt)


def _unit(n: int, i: int) -> np.ndarray:
    out = np.zeros(n)
    out[i] = 1.0
    return out
