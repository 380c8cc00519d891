"""Design check of an actuator: loop margins, stability under every single fault, HF-vs-LF agreement.

What a user runs on a new ``conf/actuator/*.yaml`` before generating data with it
(``scripts/check_actuator.py``):

1. **Linear analysis** (:func:`~phm_torch.assessment.linear.linear_loop`): the sampled-data loop without
   dry friction and backlash, at nominal and at both ends of the gain drift k8.
2. **Measured margins** (the assessment's own measurement, :class:`FrequencyResponse` of the nonlinear LF
   model): gain margin, phase margin, crossover and -3 dB bandwidth of the nominal actuator and of every
   single fault at k = 1 (:func:`single_fault_cases`).
3. **Time domain**: a step of the command's amplitude and the test command itself on the LF model for
   every case, and on the HF test bench for the cases asked; bounded, not diverging, tracking.
4. **HF vs LF**: NRMSE of the filtered envelope current and of the position between the two fidelities
   on the test command.

"Stable" for a case means: gain and phase margin > 0 where measured (a phase that never reaches -180 deg
on the grid is no gain-margin limit), and every step response bounded and not growing
(:func:`step_metrics`). Where the faulted play is wider than the sweep amplitude (k2 = 1 on most actuators)
the first harmonic measures the backlash hunting, not the loop (its margins change with the number of
cycles simulated): such a row is marked ``frequency_response_valid: false`` and judged on the time-domain
checks alone. Nothing here knows the reference actuator: every scale (test frequencies, sweep
amplitude, step length, thresholds) derives from the ``ActuatorParams`` and the command given.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch

from ..command import Chirp, SlewedChirp
from ..faults import FAULT_NAMES
from ..metrics import chirp_last_cycle, nrmse
from ..params import ActuatorParams
from ..plant import build_plant
from ..simulator import EMASimulator, Signals
from .frequency_response import FrequencyResponse
from .linear import linear_loop
from .margins import Margins, margins
from .sweep import SineSweep

FAULT_EXTREMES = {
    "k1": (0, 1.0),
    "k2": (1, 1.0),
    "k3": (2, 1.0),
    "k4": (3, 1.0),
    "k5": (4, 1.0),
    "k6": (5, 1.0),
    "k8=0": (7, 0.0),
    "k8=1": (7, 1.0),
}
# k7 is the phase of the eccentricity: only visible with k6 > 0, every value is a worst end.
ECCENTRICITY_PHASES = (0.0, 0.25, 0.75)


@dataclass(frozen=True)
class CheckRequirements:
    """Thresholds of the design check.

    Attributes:
        gain_margin_db: minimum gain margin at nominal [dB].
        phase_margin_deg: minimum phase margin at nominal [deg].
        max_growth: largest ratio of the step-response error's peak over the last quarter of the record to
            its peak over the quarter before; above it the response is called diverging [-].
        max_excursion: largest |position| / step amplitude of a bounded step response [-].
    """

    gain_margin_db: float = 6.0
    phase_margin_deg: float = 45.0
    max_growth: float = 1.5
    max_excursion: float = 3.0

    def __post_init__(self) -> None:
        for name in ("gain_margin_db", "phase_margin_deg", "max_growth", "max_excursion"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
                raise ValueError(f"requirements.{name} must be a finite number, got {v!r}")
        if self.max_growth <= 0 or self.max_excursion <= 1:
            raise ValueError(
                f"requirements.max_growth must be > 0 and max_excursion > 1, got "
                f"{self.max_growth} and {self.max_excursion}"
            )


def single_fault_cases(nominal: Sequence[float]) -> dict[str, list[float]]:
    """Nominal and each fault at its worst end, one at a time: {name: fault vector (8,)}.

    k1..k6 at 1, k8 at 0 and 1; k7 (a phase) at several values with k6 = 1 (``k6`` keeps the nominal k7).
    """
    k0 = [float(v) for v in nominal]
    if len(k0) != len(FAULT_NAMES):
        raise ValueError(f"nominal_faults must have {len(FAULT_NAMES)} entries, got {len(k0)}")
    cases = {"nominal": k0}
    for name, (i, v) in FAULT_EXTREMES.items():
        k = list(k0)
        k[i] = v
        cases[name] = k
        if name == "k6":
            for phase in ECCENTRICITY_PHASES:
                kp = list(k)
                kp[6] = phase
                cases[f"k6,k7={phase:g}"] = kp
    return cases


def linear_figures(params: ActuatorParams, position_gain_scale: float = 1.0) -> dict[str, float]:
    """Margins [Hz, deg, dB] of the linearised loop on a fine grid up to the control Nyquist frequency, and
    the closed loop's spectral radius (< 1: stable)."""
    lp = linear_loop(params, position_gain_scale)
    fine = np.geomspace(params.pwm_frequency * 1e-5, 0.499 * params.pwm_frequency, 4000)
    l_resp, t_resp = lp.response(fine)
    m = margins(torch.as_tensor(fine), torch.as_tensor(l_resp)[None], torch.as_tensor(t_resp)[None])
    out = {k: float(v[0]) for k, v in m.as_dict().items()}
    out["spectral_radius"] = float(np.abs(np.linalg.eigvals(lp.closed.A)).max())
    return out


def default_frequencies(params: ActuatorParams, points: int = 14) -> tuple[float, ...]:
    """Log-spaced test grid [Hz] from the linear crossover / 4 (covers k8 = 0, which halves the loop gain,
    and the friction's loss of gain) to 2 x max(phase crossover, bandwidth) (faults that move the phase
    crossover up), capped at a quarter of the control rate."""
    fig = linear_figures(params)
    if not math.isfinite(fig["crossover_hz"]):
        raise ValueError(
            "actuator: the linearised nominal loop has no gain crossover below the control Nyquist "
            "frequency; pass the test frequencies explicitly"
        )
    top = max(v for v in (fig["phase_crossover_hz"], fig["bandwidth_hz"], 2 * fig["crossover_hz"]) if math.isfinite(v))
    f_lo, f_hi = fig["crossover_hz"] / 4.0, min(2.0 * top, params.pwm_frequency / 4.0)
    return tuple(float(f"{f:.4g}") for f in np.geomspace(f_lo, f_hi, points))


def default_sweep_amplitude(params: ActuatorParams, command_amplitude: float) -> float:
    """Sweep amplitude [rad]: a tenth of the test command, capped so that the proportional path's current
    demand at high frequency, K_w K_pos a (x 1.5 at k8 = 1), stays below half the current limit (the margins
    of the unsaturated loop)."""
    cap = 0.5 * params.current_limit / (1.5 * params.speed_gain * params.position_gain)
    return float(f"{min(0.1 * command_amplitude, cap):.3g}")


def step_duration(params: ActuatorParams) -> float:
    """Step-test length [s]: 2.5 periods of the linear crossover (>= 15 closed-loop time constants), at least
    0.1 s, rounded up to 10 ms and then to a whole number of control periods and acquisition samples (a
    16.384 kHz PWM has no whole number of periods in 10 ms)."""
    fc = linear_figures(params)["crossover_hz"]
    t = math.ceil(max(0.1, 2.5 / fc) * 100 - 1e-9) / 100 if math.isfinite(fc) and fc > 0 else 0.1
    periods = math.ceil(t * params.pwm_frequency - 1e-6)
    # a whole number of samples too: a rate below the PWM frequency takes one every (f_pwm / f_s) periods
    every = max(1, round(params.pwm_frequency / params.sample_rate))
    return math.ceil(periods / every) * every / params.pwm_frequency


def step_metrics(
    time_s: torch.Tensor, position: torch.Tensor, amplitude: float, requirements: CheckRequirements
) -> dict[str, torch.Tensor]:
    """Step-response figures per record.

    Args:
        time_s: (n,) [s].  position: (B, n) LVDT reading [rad] after a step of ``amplitude`` [rad] at t = 0.
    Returns:
        {name: (B,)}: ``overshoot`` [fraction of the step], ``settling_s`` (last exit from a 2 % band;
        nan when never inside), ``final_error`` (mean error over the last quarter) and ``residual`` (its peak
        |error| there), both [fraction of the step], ``growth`` (see :class:`CheckRequirements`), ``bounded``
        and ``stable`` (bool as 0/1).
    """
    e = (position - amplitude) / amplitude
    n = e.shape[-1]
    q3, q4 = e[:, n // 2 : 3 * n // 4], e[:, 3 * n // 4 :]
    finite = torch.isfinite(position).all(-1)
    peak3 = q3.abs().amax(-1)
    peak4 = q4.abs().amax(-1)
    # a residual below 1e-3 of the step is settled whatever its ratio (numerical noise)
    growth = torch.where(peak4 < 1e-3, torch.zeros_like(peak4), peak4 / peak3.clamp(min=1e-3))
    outside = e.abs() > 0.02
    idx = torch.arange(n, device=e.device).expand_as(e)
    last_out = torch.where(outside, idx, torch.full_like(idx, -1)).amax(-1)
    settled = last_out < n - 1
    settling = torch.where(settled, time_s[(last_out + 1).clamp(max=n - 1)], torch.full_like(peak4, math.nan))
    bounded = finite & (position.abs().amax(-1) <= requirements.max_excursion * amplitude)
    stable = bounded & (growth <= requirements.max_growth)
    return {
        "overshoot": (position.amax(-1) / amplitude - 1.0).clamp(min=0.0),
        "settling_s": settling,
        "final_error": q4.mean(-1),
        "residual": peak4,
        "growth": growth,
        "bounded": bounded.double(),
        "stable": stable.double(),
    }


def tracking_metrics(sig: Signals, command: Callable, end_stop_angle: float) -> dict[str, torch.Tensor]:
    """Tracking of the test command per record: error RMS and max [fraction of the command's peak], bounded,
    and for a chirp starting at 0 Hz the last cycle's amplitude ratio and lag [deg]."""
    pos, cmd = sig["position"], sig["command"]
    peak = cmd.abs().amax(-1).clamp(min=1e-30)
    err = pos - cmd
    out = {
        "error_rms": err.pow(2).mean(-1).sqrt() / peak,
        "error_max": err.abs().amax(-1) / peak,
        "peak_current_A": sig["current"].abs().amax(-1),
        "peak_speed_rad_s": sig["speed"].abs().amax(-1),
        "bounded": (torch.isfinite(pos).all(-1) & (sig["user_angle"].abs().amax(-1) < end_stop_angle)).double(),
    }
    if isinstance(command, (Chirp, SlewedChirp)) and command.f_start == 0 and command.f_end > 0:
        ramp = getattr(command, "slew_rate", 0.0) * sig.time  # a slewed chirp's ramp, out of both (the fit's offset
        last = [  # term takes the position's constant lag behind it)
            chirp_last_cycle(sig.time, cmd[b] - ramp, pos[b] - ramp, command.f_end, command.duration)
            for b in range(pos.shape[0])
        ]
        out["last_cycle_ratio"] = torch.tensor([r for r, _ in last], dtype=torch.float64)
        out["last_cycle_lag_deg"] = torch.tensor([lag for _, lag in last], dtype=torch.float64)
    return out


def _rows(names: Sequence[str], table: Mapping[str, torch.Tensor], digits: int = 5) -> dict[str, dict[str, float]]:
    return {name: {k: round(float(v[i]), digits) for k, v in table.items()} for i, name in enumerate(names)}


def _step_command(amplitude: float) -> Callable[[torch.Tensor], torch.Tensor]:
    def command(t: torch.Tensor) -> torch.Tensor:
        return torch.full_like(t, amplitude)

    return command


class ActuatorCheck:
    """Runs the design check of one actuator and test command.

    Args:
        params: the actuator.
        command: the test command (a callable of time with a ``duration`` [s] and an ``amplitude`` [rad]).
        frequencies: sweep grid [Hz] (default :func:`default_frequencies`).
        sweep_amplitude: [rad] (default :func:`default_sweep_amplitude`).
        requirements: thresholds.
        hf_cases: names of :func:`single_fault_cases` also simulated on the HF test bench (step and command);
            ``None``: all; empty: no HF run.
        cycles, measure_cycles: sweep cycles simulated and measured per frequency.
        log: progress printer (``None``: silent).
    """

    def __init__(
        self,
        params: ActuatorParams,
        command: Any,
        frequencies: Sequence[float] | None = None,
        sweep_amplitude: float | None = None,
        requirements: CheckRequirements | None = None,
        hf_cases: Sequence[str] | None = None,
        cycles: int = 4,
        measure_cycles: int = 2,
        log: Callable[[str], None] | None = None,
    ):
        for attr in ("duration", "amplitude"):
            value = getattr(command, attr, None)
            if not isinstance(value, (int, float)) or not math.isfinite(value) or value <= 0:
                raise ValueError(f"command.{attr} must be a positive number, got {value!r}")
        self.params, self.command = params, command
        self.cases = single_fault_cases(params.nominal_faults)
        unknown = sorted(set(hf_cases or ()) - set(self.cases))
        if unknown:
            raise ValueError(f"hf_cases: unknown case(s) {unknown}; known: {list(self.cases)}")
        self.hf_cases = list(self.cases) if hf_cases is None else list(hf_cases)
        self.requirements = requirements or CheckRequirements()
        freqs = tuple(frequencies) if frequencies is not None else default_frequencies(params)
        amp = sweep_amplitude if sweep_amplitude is not None else default_sweep_amplitude(params, command.amplitude)
        self.sweep = SineSweep(
            frequencies=freqs,
            amplitude=amp,
            cycles=cycles,
            measure_cycles=measure_cycles,
            min_duration=0.0,
            substeps=1,
            group_size=4,
            compile=False,
        )
        self.step_amplitude = float(command.amplitude)
        self.step_duration = step_duration(params)
        self.log = log or (lambda msg: None)

    def faults(self, names: Sequence[str]) -> torch.Tensor:
        return torch.tensor([self.cases[n] for n in names], dtype=torch.float64)

    def measured_margins(self) -> Margins:
        """LF-measured margins of every case (B = number of cases)."""
        response = FrequencyResponse(self.params, self.sweep)
        return response.margins_of(response.read(self.faults(list(self.cases))))

    def simulate(self, fidelity: str, names: Sequence[str]) -> tuple[Signals, Signals]:
        """(step, command) records of ``names`` on one fidelity."""
        sim = EMASimulator(self.params, fidelity)
        k = self.faults(names)
        chans = ["position", "current", "speed", "user_angle"]
        with torch.no_grad():
            step = sim.run(k, _step_command(self.step_amplitude), self.step_duration, channels=chans)
            test = sim.run(k, self.command, float(self.command.duration), channels=chans)
        return step, test

    def run(self) -> dict[str, Any]:
        """The whole check as a JSON-able report (see ``scripts/check_actuator.py``)."""
        req, names = self.requirements, list(self.cases)
        t0 = time.perf_counter()
        linear = {
            name: linear_figures(self.params, scale) for name, scale in (("nominal", 1.0), ("k8=0", 0.5), ("k8=1", 1.5))
        }
        self.log(f"linear loop: {linear['nominal']}")
        m = self.measured_margins()
        self.log(f"LF sweep: {time.perf_counter() - t0:.1f} s")
        lf_step, lf_test = self.simulate("lf", names)
        self.log(f"LF step and command: {time.perf_counter() - t0:.1f} s")
        lf_sm = step_metrics(lf_step.time, lf_step["position"], self.step_amplitude, req)
        lf_tm = tracking_metrics(lf_test, self.command, self.params.end_stop_angle)
        hf: dict[str, Any] = {}
        agreement: dict[str, dict[str, float]] = {}
        if self.hf_cases:
            idx = [names.index(n) for n in self.hf_cases]
            hf_step, hf_test = self.simulate("hf", self.hf_cases)
            self.log(f"HF step and command ({len(idx)} cases): {time.perf_counter() - t0:.1f} s")
            hf_sm = step_metrics(hf_step.time, hf_step["position"], self.step_amplitude, req)
            hf = {
                "step": _rows(self.hf_cases, hf_sm),
                "command": _rows(self.hf_cases, tracking_metrics(hf_test, self.command, self.params.end_stop_angle)),
            }
            cur = nrmse(lf_test["current"][idx], hf_test["current"])
            pos = nrmse(lf_test["position"][idx], hf_test["position"])
            step_pos = nrmse(lf_step["position"][idx], hf_step["position"])
            agreement = {
                n: {
                    "current_nrmse": round(float(cur[j]), 5),
                    "position_nrmse": round(float(pos[j]), 6),
                    "step_position_nrmse": round(float(step_pos[j]), 6),
                }
                for j, n in enumerate(self.hf_cases)
            }
        margins_rows = _rows(names, m.as_dict(), 3)
        table: dict[str, dict[str, Any]] = {}
        plays = build_plant(self.params, self.faults(names)).backlash  # the faulted play of each case [rad]
        for i, n in enumerate(names):
            gm, pm = float(m.gain_margin_db[i]), float(m.phase_margin_deg[i])
            valid = float(plays[i]) <= self.sweep.amplitude
            fr_stable = (pm > 0) and not (gm <= 0) or not valid  # nan gain margin: no phase crossover on the grid
            row = {
                "k": self.cases[n],
                **margins_rows[n],
                "frequency_response_valid": valid,
                "lf_step_stable": bool(lf_sm["stable"][i]),
                "lf_command_bounded": bool(lf_tm["bounded"][i]),
            }
            if n in hf.get("step", {}):
                row["hf_step_stable"] = bool(hf["step"][n]["stable"])
                row["hf_command_bounded"] = bool(hf["command"][n]["bounded"])
            row["stable"] = bool(
                fr_stable
                and row["lf_step_stable"]
                and row["lf_command_bounded"]
                and row.get("hf_step_stable", True)
                and row.get("hf_command_bounded", True)
            )
            table[n] = row
        nom = table["nominal"]
        verdict = {
            "nominal_gain_margin": nom["gain_margin_db"] >= req.gain_margin_db,
            "nominal_phase_margin": nom["phase_margin_deg"] >= req.phase_margin_deg,
            "linear_gain_margin": linear["nominal"]["gain_margin_db"] >= req.gain_margin_db,
            "linear_phase_margin": linear["nominal"]["phase_margin_deg"] >= req.phase_margin_deg,
            "every_single_fault_stable": all(r["stable"] for r in table.values()),
        }
        verdict["pass"] = all(verdict.values())
        return {
            "requirements": vars(req),
            "sweep": {
                "frequencies": list(self.sweep.frequencies),
                "amplitude": self.sweep.amplitude,
                "cycles": self.sweep.cycles,
                "measure_cycles": self.sweep.measure_cycles,
            },
            "step": {"amplitude": self.step_amplitude, "duration": self.step_duration},
            "linear": {k: {n: round(v, 4) for n, v in d.items()} for k, d in linear.items()},
            "single_faults": table,
            "lf": {"step": _rows(names, lf_sm), "command": _rows(names, lf_tm)},
            "hf": hf,
            "agreement": agreement,
            "verdict": verdict,
            "elapsed_s": round(time.perf_counter() - t0, 1),
        }


__all__ = [
    "ActuatorCheck",
    "CheckRequirements",
    "default_frequencies",
    "default_sweep_amplitude",
    "linear_figures",
    "single_fault_cases",
    "step_metrics",
    "tracking_metrics",
]
