"""Frequency response of the position loop from batched sinusoidal simulations of the LF model.

The actuator is nonlinear (dry friction, backlash, saturations), so its "Bode diagram" is measured the
way a test bench would: one sinusoidal command per test frequency, the response's first harmonic
taken by a discrete Fourier correlation over whole cycles once the transient has decayed.

Open loop by direct loop breaking: the position error e = theta_cmd - theta_lvdt that drives the
controller is a signal of the simulation, so L(jw) = Theta_lvdt(jw) / E(jw) is measured in closed
loop without opening it (which would let the integrating plant drift). This is algebraically the
same as L = T / (1 - T) with T = Theta_lvdt / Theta_cmd, but computed from the two first harmonics it
does not divide by the small 1 - T of the low frequencies.

Batching: the frequencies are taken ``group_size`` at a time; one simulator call simulates every
fault vector at every frequency of the group (batch B * group_size, simulated for the longest test of
the group, the higher frequencies simply getting more settling cycles). Large batches amortise the
per-period cost of the simulator loop, and a compiled simulator is compiled once (every call has the
same batch size: the last group is padded by repeating its last frequency).
"""

from __future__ import annotations

import dataclasses
import itertools
import math
from dataclasses import dataclass, field

import torch

from ..faults import as_fault_tensor
from ..params import ActuatorParams
from ..simulator import EMASimulator
from .design import AUTO, SweepDesign


@dataclass(frozen=True)
class SineSweep:
    """The test signals of the frequency-response measurement.

    Attributes:
        frequencies: test frequencies [Hz], increasing; each is snapped so that ``measure_cycles``
            cycles span a whole number of control periods (no spectral leakage). ``"auto"``: derived from
            the actuator's linearised loop by ``design`` (:meth:`resolve`).
        amplitude: command amplitude [rad, user side], the same at every frequency; ``"auto"``: derived
            from the actuator's friction, play, stroke and limits by ``design``.
        cycles: cycles simulated per frequency (from rest), the last ``measure_cycles`` measured.
        measure_cycles: cycles in the Fourier window.
        min_duration: shortest simulation [s] (lets the closed-loop transient decay at high frequency).
        substeps: LF substeps per control period.
        group_size: frequencies simulated together in one batch.
        compile: fuse the simulator substep with ``torch.compile`` (worth it for batches >~ 256).
        design: how the ``"auto"`` values are derived (:class:`~phm_torch.assessment.design.SweepDesign`).
    """

    frequencies: tuple[float, ...] | str
    amplitude: float | str
    cycles: int
    measure_cycles: int
    min_duration: float
    substeps: int
    group_size: int
    compile: bool
    design: SweepDesign = field(default_factory=SweepDesign)

    def __post_init__(self) -> None:
        if isinstance(self.frequencies, str):
            if self.frequencies != AUTO:
                raise ValueError(
                    f"assessment.sweep.frequencies must be a list of frequencies [Hz] or "
                    f"'{AUTO}', got {self.frequencies!r}"
                )
        else:
            try:
                freqs = tuple(float(f) for f in self.frequencies)
            except (TypeError, ValueError):
                raise ValueError(
                    f"assessment.sweep.frequencies must be a list of frequencies [Hz] or "
                    f"'{AUTO}', got {self.frequencies!r}"
                ) from None
            object.__setattr__(self, "frequencies", freqs)
            if len(freqs) < 2:
                raise ValueError(f"assessment.sweep.frequencies needs at least 2 values, got {list(freqs)}")
            if any(not math.isfinite(f) or f <= 0 for f in freqs) or any(b <= a for a, b in itertools.pairwise(freqs)):
                raise ValueError(f"assessment.sweep.frequencies must be positive and increasing, got {list(freqs)}")
        if isinstance(self.amplitude, str):
            if self.amplitude != AUTO:
                raise ValueError(
                    f"assessment.sweep.amplitude must be a number [rad] or '{AUTO}', got {self.amplitude!r}"
                )
        elif (
            isinstance(self.amplitude, bool)
            or not isinstance(self.amplitude, (int, float))
            or not (math.isfinite(self.amplitude) and self.amplitude > 0)
        ):
            raise ValueError(f"assessment.sweep.amplitude must be > 0 [rad], got {self.amplitude}")
        if not isinstance(self.design, SweepDesign):
            raise ValueError(f"assessment.sweep.design must be a SweepDesign, got {self.design!r}")
        if int(self.measure_cycles) != self.measure_cycles or self.measure_cycles < 1:
            raise ValueError(f"assessment.sweep.measure_cycles must be an integer >= 1, got {self.measure_cycles}")
        if int(self.cycles) != self.cycles or self.cycles <= self.measure_cycles:
            raise ValueError(
                f"assessment.sweep.cycles must be an integer > measure_cycles "
                f"({self.measure_cycles}), got {self.cycles}"
            )
        if not (math.isfinite(self.min_duration) and self.min_duration >= 0):
            raise ValueError(f"assessment.sweep.min_duration must be >= 0 [s], got {self.min_duration}")
        if int(self.substeps) != self.substeps or self.substeps < 1:
            raise ValueError(f"assessment.sweep.substeps must be an integer >= 1, got {self.substeps}")
        if int(self.group_size) != self.group_size or self.group_size < 1:
            raise ValueError(f"assessment.sweep.group_size must be an integer >= 1, got {self.group_size}")

    @property
    def is_resolved(self) -> bool:
        """Both the frequencies and the amplitude are numbers (no ``"auto"``)."""
        return not isinstance(self.frequencies, str) and not isinstance(self.amplitude, str)

    def resolve(self, params: ActuatorParams) -> SineSweep:
        """This sweep with ``"auto"`` frequencies and amplitude derived for ``params`` (explicit values win)."""
        if self.is_resolved:
            return self
        freqs = self.design.frequencies(params) if isinstance(self.frequencies, str) else self.frequencies
        amp = self.design.amplitude(params, freqs[-1]) if isinstance(self.amplitude, str) else self.amplitude
        return dataclasses.replace(self, frequencies=freqs, amplitude=amp)


@dataclass
class LoopResponse:
    """Measured first-harmonic responses.

    Attributes:
        frequencies: (F,) actual test frequencies [Hz].
        open_loop: (B, F) complex L(jw) = Theta_lvdt / E.
        closed_loop: (B, F) complex T(jw) = Theta_lvdt / Theta_cmd.
    """

    frequencies: torch.Tensor
    open_loop: torch.Tensor
    closed_loop: torch.Tensor


class FrequencyResponse:
    """Measures L(jw) and T(jw) of a batch of LF actuators.

    Args:
        params: actuator datasheet; the measurement samples the LVDT once per control period (at the
            instants the controller samples it), whatever ``params.sample_rate``.
        sweep: the test signals (``"auto"`` values resolved for ``params``).
        device: where to simulate (float64).
    """

    def __init__(self, params: ActuatorParams, sweep: SineSweep, device: str | torch.device = "cpu"):
        self.params = params.replace(sample_rate=params.pwm_frequency)
        self.sweep = sweep = sweep.resolve(params)
        self.device = torch.device(device)
        self.sim = EMASimulator(
            self.params, "lf", substeps=int(sweep.substeps), device=self.device, compile=bool(sweep.compile)
        )
        f_ctrl = self.params.pwm_frequency
        plan = []
        for f in sweep.frequencies:
            window = max(1, round(sweep.measure_cycles * f_ctrl / f))  # control periods measured
            f_true = sweep.measure_cycles * f_ctrl / window
            periods = max(math.ceil(sweep.cycles * f_ctrl / f_true), math.ceil(sweep.min_duration * f_ctrl), window)
            plan.append((f_true, window, periods))
        self.plan = plan

    @property
    def frequencies(self) -> torch.Tensor:
        """(F,) the snapped test frequencies [Hz]."""
        return torch.tensor([f for f, _, _ in self.plan], dtype=torch.float64)

    @property
    def groups(self) -> list[list[int]]:
        """Indices of the test frequencies simulated together (the last group padded with its last index)."""
        g, n = int(self.sweep.group_size), len(self.plan)
        out = [list(range(i, min(i + g, n))) for i in range(0, n, g)]
        out[-1] += [out[-1][-1]] * (g - len(out[-1]))
        return out

    @property
    def periods_per_vector(self) -> int:
        """Simulated control periods per fault vector (the cost of one assessment)."""
        return sum(len(grp) * max(self.plan[i][2] for i in grp) for grp in self.groups)

    def measure(self, faults: torch.Tensor) -> LoopResponse:
        """Frequency response of every fault vector.

        Args:
            faults: (B, 8) fault vectors in [0, 1].
        Returns:
            The responses at the F test frequencies.
        """
        k = as_fault_tensor(faults, torch.float64, self.device)
        b = k.shape[0]
        f_ctrl = self.params.pwm_frequency
        amp = float(self.sweep.amplitude)
        l_cols: dict[int, torch.Tensor] = {}
        t_cols: dict[int, torch.Tensor] = {}
        for grp in self.groups:
            periods = max(self.plan[i][2] for i in grp)
            t = torch.arange(periods + 1, dtype=torch.float64, device=self.device) / f_ctrl
            w = torch.tensor([2.0 * math.pi * self.plan[i][0] for i in grp], dtype=torch.float64, device=self.device)
            w_rows = w.repeat_interleave(b)  # rows g * B + b: frequency grp[g], fault vector b

            def command(times: torch.Tensor, w_rows: torch.Tensor = w_rows) -> torch.Tensor:
                # (G * B, n) as the transpose of a contiguous (n, G * B): the simulator reads one column
                # per control period, contiguous whatever n, so a compiled step is not specialised on n.
                return (amp * torch.sin(times[:, None] * w_rows[None, :])).T

            with torch.no_grad():
                sig = self.sim.run(k.repeat(len(grp), 1), command, periods / f_ctrl, channels=["position"])
            y_all = sig["position"].view(len(grp), b, -1)
            for g, i in enumerate(grp):
                if i in l_cols:
                    continue
                window = self.plan[i][1]
                # the window of whole cycles ending one period before the last sample
                sl = slice(periods - window, periods)
                phase = w[g] * t[sl]
                basis = torch.complex(torch.cos(phase), -torch.sin(phase))
                y_h = (y_all[g, :, sl].to(basis.dtype) * basis).sum(-1)
                r_h = (amp * torch.sin(phase)).to(basis.dtype).mul(basis).sum(-1).expand(b)
                l_cols[i] = y_h / (r_h - y_h)
                t_cols[i] = y_h / r_h
        order = range(len(self.plan))
        return LoopResponse(
            self.frequencies.to(self.device),
            torch.stack([l_cols[i] for i in order], -1),
            torch.stack([t_cols[i] for i in order], -1),
        )
