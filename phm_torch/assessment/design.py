"""The sine sweep of the assessment derived from the actuator itself (``frequencies: auto``, ``amplitude: auto``).

**Frequencies.** The linearised nominal loop (:func:`~phm_torch.assessment.linear.linear_loop`: no dry
friction, no backlash) gives the gain crossover f_c, the phase crossover f_180 and the closed-loop -3 dB
bandwidth f_bw on a fine grid up to the control Nyquist frequency. The test grid spans

    f_lo = f_c / low_margin,    f_hi = max(f_180, f_bw) * high_margin    (capped at f_ctrl / 4),

log-spaced at ``points_per_decade``. When the speed limit cannot carry the test amplitude (below) up to f_hi, the
top comes down to the frequency where it can, but not below max(f_180, f_bw) * min_high_margin (a stiff, fast
loop behind a long-stroke transmission, e.g. a ball screw whose user side is in metres: its phase crossover is
high and its gear ratio large). The lower margin covers the dry friction, which at a small test
amplitude lowers the measured crossover (reference: 28 -> 20.5 Hz), and the loss of loop gain of the
degraded actuators whose bandwidth still matters; the upper one covers the measurement's own phase lag
and the faults that move the phase crossover up. Defaults 2.3 / 1.8 / 12 per decade reproduce the span
(12-160 Hz) and density (14 points) of the grid tuned by hand for the reference actuator, now as ratios
to the loop of whatever actuator is given.

**Amplitude.** The test must be large enough that the motor breaks away from its dry friction and the
nominal play does not dominate, and small against the stroke and the drive's limits:

    a_friction = T_s / (2 k_e K_w K_pos)     (user-side position error at which the proportional path
                                              of the cascade commands the break-away torque),
    lower = max(friction_factor * a_friction, backlash_factor * b_0),
    upper = min(stroke_fraction * theta_stop,
                limit_fraction * omega_max / (2 pi f_hi N),      (motor speed at the top frequency)
                limit_fraction * I_max / (K_w K_pos)),           (current of the proportional path)

and the amplitude is ``lower`` (a small amplitude keeps friction and backlash visible, as they are for the
fine positioning of a flight control), or a ValueError naming the field when lower > upper. With the
default friction_factor 4 the reference actuator gets 7.96e-5 rad (hand-tuned: 8e-5).

Only ``ActuatorParams`` enter; nothing of the reference actuator is built in.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch

from ..params import ActuatorParams
from .linear import linear_loop
from .margins import margins

AUTO = "auto"


@dataclass(frozen=True)
class SweepDesign:
    """How ``frequencies: auto`` and ``amplitude: auto`` are derived from the actuator (module docstring).

    Attributes:
        low_margin: f_lo = linear gain crossover / low_margin [-], > 1.
        high_margin: f_hi = max(linear phase crossover, linear -3 dB bandwidth) * high_margin [-], > 1.
        min_high_margin: the speed limit may lower f_hi to max(phase crossover, bandwidth) * min_high_margin,
            no lower [-], in (1, high_margin].
        points_per_decade: density of the log-spaced grid [1/decade].
        friction_factor: amplitude = friction_factor * the break-away position error [-].
        backlash_factor: amplitude >= backlash_factor * the nominal play [-].
        stroke_fraction: amplitude <= stroke_fraction * the end-stop angle [-].
        limit_fraction: the test uses at most this fraction of the speed and current limits [-].
    """

    low_margin: float = 2.3
    high_margin: float = 1.8
    min_high_margin: float = 1.25
    points_per_decade: float = 12.0
    friction_factor: float = 4.0
    backlash_factor: float = 10.0
    stroke_fraction: float = 0.01
    limit_fraction: float = 0.5

    def __post_init__(self) -> None:
        for name in (
            "low_margin",
            "high_margin",
            "min_high_margin",
            "points_per_decade",
            "friction_factor",
            "backlash_factor",
            "stroke_fraction",
            "limit_fraction",
        ):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
                raise ValueError(f"assessment.sweep.design.{name} must be a finite number, got {v!r}")
        for name in ("low_margin", "high_margin"):
            if getattr(self, name) <= 1.0:
                raise ValueError(f"assessment.sweep.design.{name} must be > 1, got {getattr(self, name)}")
        if not 1.0 < self.min_high_margin <= self.high_margin:
            raise ValueError(
                f"assessment.sweep.design.min_high_margin must be in (1, high_margin={self.high_margin}], "
                f"got {self.min_high_margin}"
            )
        if self.points_per_decade < 2:
            raise ValueError(f"assessment.sweep.design.points_per_decade must be >= 2, got {self.points_per_decade}")
        if self.friction_factor <= 0 or self.backlash_factor < 0:
            raise ValueError(
                f"assessment.sweep.design.friction_factor must be > 0 and backlash_factor >= 0, "
                f"got {self.friction_factor} and {self.backlash_factor}"
            )
        for name in ("stroke_fraction", "limit_fraction"):
            if not 0 < getattr(self, name) <= 1:
                raise ValueError(f"assessment.sweep.design.{name} must be in (0, 1], got {getattr(self, name)}")

    # -- the loop --------------------------------------------------------------------------------------
    @staticmethod
    def loop_figures(params: ActuatorParams) -> dict[str, float]:
        """Margins of the linearised nominal loop on a fine grid (0.1 mHz x f_ctrl .. Nyquist): crossover_hz,
        phase_margin_deg, phase_crossover_hz, gain_margin_db, bandwidth_hz.

        Raises:
            ValueError: the linear nominal loop is unstable or has no crossover below Nyquist.
        """
        lp = linear_loop(params)
        if np.abs(np.linalg.eigvals(lp.closed.A)).max() >= 1.0:
            raise ValueError(
                "assessment.sweep: auto: the linearised nominal position loop of the actuator is unstable, so no "
                "sweep can measure its margins; retune its loop gains (position_gain, speed_gain, current_gain and "
                "their integral gains; scripts/check_actuator.py reports the loop)"
            )
        f_ctrl = params.pwm_frequency
        fine = np.geomspace(f_ctrl * 1e-5, 0.499 * f_ctrl, 4000)
        l_resp, t_resp = lp.response(fine)
        m = margins(torch.as_tensor(fine), torch.as_tensor(l_resp)[None], torch.as_tensor(t_resp)[None])
        out = {k: float(v[0]) for k, v in m.as_dict().items()}
        for name in ("crossover_hz", "phase_crossover_hz"):
            if not math.isfinite(out[name]):
                raise ValueError(
                    f"assessment.sweep: auto: the linearised nominal loop has no {name} below the "
                    f"control Nyquist frequency ({0.5 * f_ctrl:g} Hz); set "
                    f"assessment.sweep.frequencies explicitly"
                )
        if not math.isfinite(out["bandwidth_hz"]):  # above -3 dB up to Nyquist: the phase crossover bounds it
            out["bandwidth_hz"] = out["phase_crossover_hz"]
        return out

    # -- the grid --------------------------------------------------------------------------------------
    def frequencies(
        self, params: ActuatorParams, figures: dict[str, float] | None = None, amplitude: float | None = None
    ) -> tuple[float, ...]:
        """The log-spaced test frequencies [Hz] bracketing the nominal loop (4 significant digits), their top
        lowered (to no less than ``min_high_margin``) where the speed limit cannot carry ``amplitude`` [rad] there
        (default: the derived amplitude's lower bound)."""
        fig = figures or self.loop_figures(params)
        f_lo = fig["crossover_hz"] / self.low_margin
        f_top = max(fig["phase_crossover_hz"], fig["bandwidth_hz"])
        f_hi = min(f_top * self.high_margin, params.pwm_frequency / 4)
        amp = self.lower_amplitude(params) if amplitude is None else amplitude
        # 0.999: the grid is rounded to 4 significant digits, which must not lift its top past the speed bound
        f_speed = 0.999 * self.limit_fraction * params.speed_limit / (2.0 * math.pi * amp * params.gear_ratio)
        if f_speed < f_hi:  # the speed limit would cap the amplitude at the top: bring the top down instead
            f_hi = min(f_hi, max(f_speed, f_top * self.min_high_margin))
        if f_hi <= f_lo * 1.5:
            raise ValueError(
                f"assessment.sweep: auto: derived band [{f_lo:.4g}, {f_hi:.4g}] Hz is too narrow "
                f"(control rate {params.pwm_frequency:g} Hz); set assessment.sweep.frequencies"
            )
        n = math.ceil(self.points_per_decade * math.log10(f_hi / f_lo) - 1e-9) + 1
        return tuple(float(f"{f:.4g}") for f in np.geomspace(f_lo, f_hi, n))

    # -- the amplitude ---------------------------------------------------------------------------------
    def amplitude_bounds(self, params: ActuatorParams, f_max: float) -> dict[str, float]:
        """The bounds of the module docstring [rad, user side]: friction, backlash (lower), stroke, speed,
        current (upper), for a sweep whose highest frequency is ``f_max`` [Hz]."""
        p = params
        gain = p.speed_gain * p.position_gain  # A per rad of user-side position error
        a_friction = max(p.static_friction, p.coulomb_friction) / (2.0 * p.back_emf_constant * gain)
        return {
            "friction": self.friction_factor * a_friction,
            "backlash": self.backlash_factor * p.backlash,
            "stroke": self.stroke_fraction * p.end_stop_angle,
            "speed": self.limit_fraction * p.speed_limit / (2.0 * math.pi * f_max * p.gear_ratio),
            "current": self.limit_fraction * p.current_limit / gain,
        }

    def lower_amplitude(self, params: ActuatorParams) -> float:
        """The largest lower bound of the amplitude [rad] (friction, backlash); it does not depend on the grid.

        Raises:
            ValueError: the actuator has neither friction nor play, so nothing sizes the amplitude.
        """
        b = self.amplitude_bounds(params, 1.0)
        lower = max(b["friction"], b["backlash"])
        if not lower > 0:
            raise ValueError(
                "assessment.sweep.amplitude: auto: the actuator's static_friction, coulomb_friction and backlash are "
                "all 0, and the derived amplitude is sized from the break-away friction and the play; set "
                "assessment.sweep.amplitude explicitly [rad, user side] (a real drive has some friction: with none, "
                "the dry-friction fault k1, which scales it, cannot be seen either)"
            )
        return lower

    def amplitude(self, params: ActuatorParams, f_max: float) -> float:
        """The test amplitude [rad]: the largest lower bound, checked against the smallest upper bound."""
        b = self.amplitude_bounds(params, f_max)
        lower = self.lower_amplitude(params)
        upper_name = min(("stroke", "speed", "current"), key=b.__getitem__)
        if lower > b[upper_name]:
            raise ValueError(
                f"assessment.sweep.amplitude: auto: the friction/backlash need >= {lower:.3g} rad but "
                f"the {upper_name} limit allows <= {b[upper_name]:.3g} rad; set it explicitly"
            )
        return float(f"{lower:.4g}")

    def record(self, params: ActuatorParams) -> dict[str, Any]:
        """JSON-able account of the derivation: the linear loop figures, the grid and the amplitude bounds."""
        fig = self.loop_figures(params)
        freqs = self.frequencies(params, fig)
        return {
            "linear_loop": {k: round(v, 4) for k, v in fig.items()},
            "frequencies": list(freqs),
            "amplitude": self.amplitude(params, freqs[-1]),
            "amplitude_bounds": {k: float(f"{v:.4g}") for k, v in self.amplitude_bounds(params, freqs[-1]).items()},
        }
