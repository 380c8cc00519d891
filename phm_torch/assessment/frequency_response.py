"""Frequency response of the position loop from batched sinusoidal simulations of the LF model.

The actuator is nonlinear (dry friction, backlash, saturations), so its "Bode diagram" is measured the
way a test bench would: one sinusoidal command per test frequency, the response's first harmonic
taken by a discrete Fourier correlation over whole cycles once the transient has decayed.

Open loop by direct loop breaking: the position error e = theta_cmd - theta_lvdt that drives the
controller is a signal of the simulation, so L(jw) = Theta_lvdt(jw) / E(jw) is measured in closed
loop without opening it (which would let the integrating plant drift). This is algebraically the
same as L = T / (1 - T) with T = Theta_lvdt / Theta_cmd, but computed from the two first harmonics it
does not divide by the small 1 - T of the low frequencies.

Settling: the first harmonic is taken over the last ``measure_cycles`` cycles and over the
``measure_cycles`` before them; where L or T changed by more than ``tolerance`` (relative) between the two,
the response has not settled (``LoopResponse.settled``). With ``max_extensions`` > 0 such a (vector,
frequency) is simulated on from where it stopped to twice the time (the trajectory of a run that long from rest, at
half its cost), up to that many times, and counted as unsettled if it still moves. A fixed number of cycles is not enough: the transient decays with the loop's own time
constants (a lightly damped degraded loop, the slow integrator pole: ~0.1 s on the reference actuator), so
4 cycles at the upper frequencies read the transient (a degraded reference actuator at 70 Hz: |T| -2.41 dB
after 4 cycles, -1.53 dB settled) and the labels depend on how the frequencies are batched. Near and above
a degraded loop's resonance the small-amplitude response with backlash need not be periodic at all (the
same actuator at 77 Hz: -8.7, -15.6, -13.3 dB after 4, 8, 64 cycles); those stay unsettled and are counted.
The code's defaults are ``max_extensions`` 0, ``refine`` 0 (a store whose config records neither was labelled so),
and so is the shipped config: along run-to-failure paths settled readings put single non-periodic faulty readings
that no classifier learns, at 4.85-14x the cost (docs/dataset.md, "Why it is not the default").

Uncertain labels: the window before the last is read too (``LoopResponse.open_loop_before``/``closed_loop_before``),
and :class:`~phm_torch.assessment.health.AssessmentFunction` labels it as well: a vector whose two labels differ
is ``uncertain`` (its label is decided by when it is read). With the fixed 4 cycles that is a quarter of importance-
sampled reference vectors (67 of 256); settled and refined, 2 of the same 256: the floor that responses which never
become periodic put under any classifier's error.

Refinement: between grid points the crossings are interpolated (``margins.py``). ``refine`` rounds then
measure each vector again at its own interpolated gain crossover, phase crossover and -3 dB bandwidth and
read the margins off the grid with those points inserted: 3 simulations per vector and round instead of a
denser grid for every vector (on the reference actuator at 12 points per decade the interpolated bandwidth of
the vectors nearest the requirements was off by 2.7 Hz median, ~3.6 %).

Rotor position: the test amplitude is a few electrical degrees, so only the phases conducting in the rotor's sector
act (at rest at 0 a short in phase A reads the nominal margins); ``rotor_angle`` [rad, electrical] rests the
actuator elsewhere, the command offset by as much (``rotor_positions``: the worst of several, health.py).

Batching: the frequencies are taken ``group_size`` at a time; one simulator call simulates every
fault vector at every frequency of the group (batch B * group_size, simulated for the longest test of
the group, the higher frequencies simply getting more settling cycles). Large batches amortise the
per-period cost of the simulator loop, and a compiled simulator is compiled once (every call has the
same batch size: the last group is padded by repeating its last frequency; the extensions' and the refinement's
batches, whose sizes vary from call to call, are padded to a few sizes: ``padded_size``).
"""

from __future__ import annotations

import math

import torch

from ..faults import as_fault_tensor
from ..params import ActuatorParams
from ..sim_state import SimState, at_rotor_angle
from ..simulator import EMASimulator
from .margins import Margins, margins
from .readings import LoopResponse, Readings
from .sweep import SineSweep

BUCKET_MIN = 64  # smallest padded batch of a compiled extension, refinement or rotor-position simulation


def padded_size(n: int, smallest: int = BUCKET_MIN) -> int:
    """The batch size a compiled simulator reads n rows at: the smallest of smallest * 2^j and 1.5 * smallest * 2^j
    that holds them (at most a third padding), so that a few compiled sizes serve every call."""
    size = smallest
    while size < n:
        size = size * 3 // 2 if size & (size - 1) == 0 else size * 4 // 3
    return size


def padding_index(n: int, size: int, device: torch.device | str) -> torch.Tensor:
    """(size,) row index of n rows padded to ``size`` by repeating the last one (the padded rows' readings are
    dropped: a vector's reading does not depend on its batch)."""
    return torch.cat([torch.arange(n, device=device), torch.full((size - n,), n - 1, device=device)])


class FrequencyResponse:
    """Measures L(jw) and T(jw) of a batch of LF actuators.

    Args:
        params: actuator datasheet; the measurement samples the LVDT once per control period (at the
            instants the controller samples it), whatever ``params.sample_rate``.
        sweep: the test signals (``"auto"`` values resolved for ``params``).
        device: where to simulate (float64).
    """

    def __init__(
        self,
        params: ActuatorParams,
        sweep: SineSweep,
        device: str | torch.device = "cpu",
        rotor_angle: float = 0.0,
        simulator: EMASimulator | None = None,
    ):
        self.rotor_angle = float(rotor_angle)  # [rad, electrical] where the rotor rests (module docstring)
        self.params = params.replace(sample_rate=params.pwm_frequency)
        self.sweep = sweep = sweep.resolve(params)
        self.device = torch.device(device)
        # ``simulator``: another position's (the rest angle is a state and a command offset, not a simulator
        # setting), so that its compiled graphs serve every position: dynamo guards them on the instance
        self.sim = simulator or EMASimulator(
            self.params, "lf", substeps=int(sweep.substeps), device=self.device, compile=bool(sweep.compile)
        )
        self.plan = [self._test(f) for f in sweep.frequencies]
        self.extensions = 0  # responses simulated again because they had not settled
        self.unsettled = 0  # responses still moving after max_extensions

    def _test(self, f: float) -> tuple[float, int, int]:
        """(snapped frequency [Hz], measured control periods, simulated control periods) of a test at f."""
        f_ctrl = self.params.pwm_frequency
        sw = self.sweep
        window = max(1, round(sw.measure_cycles * f_ctrl / f))
        f_true = sw.measure_cycles * f_ctrl / window
        periods = max(math.ceil(sw.cycles * f_ctrl / f_true), math.ceil(sw.min_duration * f_ctrl), 2 * window)
        return f_true, window, periods

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
        """Simulated control periods per fault vector on the grid before any extension or refinement."""
        return sum(len(grp) * max(self.plan[i][2] for i in grp) for grp in self.groups)

    def _harmonics(
        self, k: torch.Tensor, f: torch.Tensor, window: torch.Tensor, periods: int, state: SimState | None = None
    ) -> tuple[Readings, SimState]:
        """One simulation of rows (k_r, f_r) for ``periods`` control periods, from rest or on from ``state`` (the
        rows' own, where an earlier call ended): L and T over each row's last ``window_r`` control periods and over
        the window before (rows R; k (R, 8), f (R,) snapped, window (R,); each (R,) complex), and the end state."""
        f_ctrl = self.params.pwm_frequency
        end = periods + (0 if state is None else round(float(state.time) * f_ctrl))  # periods since rest
        amp = float(self.sweep.amplitude)
        w = 2.0 * math.pi * f
        theta_m = self.rotor_angle / self.params.pole_pairs
        rest = theta_m / self.params.gear_ratio  # [rad, user side]: 0 unless the rotor rests elsewhere
        if state is None and theta_m:
            state = at_rotor_angle(self.sim.init(k), theta_m, self.params.gear_ratio)

        def command(times: torch.Tensor) -> torch.Tensor:
            # (R, n) as the transpose of a contiguous (n, R): the simulator reads one column per control
            # period, contiguous whatever n, so a compiled step is not specialised on n.
            wave = amp * torch.sin(times[:, None] * w[None, :])
            return (wave + rest if rest else wave).T  # at rest at 0 (the default) no extra op per call

        with torch.no_grad():
            sig = self.sim.run(k, command, periods / f_ctrl, channels=["position"], state=state)
        y = sig["position"]
        # rows sharing a window (on the grid, one per frequency) are read over exactly their two windows; rows of
        # many different windows (refinement) together over the longest, masked
        values = torch.unique(window)
        parts = [window == v for v in values] if len(values) <= 8 else [torch.ones_like(window, dtype=torch.bool)]
        out = [torch.empty(k.shape[0], dtype=torch.complex128, device=self.device) for _ in range(4)]
        for part in parts:
            rows = torch.nonzero(part)[:, 0]
            span = 2 * int(window[rows].max())  # the two windows end one period before the last sample
            read = self._two_windows(y[rows, periods - span : periods], w[rows], window[rows], end)
            for o, r in zip(out, read, strict=True):
                o[rows] = r
        return Readings(*out), sig.state

    def _two_windows(
        self, y: torch.Tensor, w: torch.Tensor, window: torch.Tensor, periods: int
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
        """L, T over each row's last ``window`` control periods, then over the window before; y (R, 2 max(window))
        the samples ending one period before the last, w (R,) [rad/s], ``periods`` simulated since rest."""
        f_ctrl = self.params.pwm_frequency
        amp = float(self.sweep.amplitude)
        span = y.shape[-1]
        t = torch.arange(periods - span, periods, dtype=torch.float64, device=self.device) / f_ctrl
        if bool((window == window[0]).all()):  # one window, so one frequency: one basis for all, no masks
            phase = w[0] * t
            basis = torch.complex(torch.cos(phase), -torch.sin(phase))
            y_b = y.to(basis.dtype) * basis
            r_b = (amp * torch.sin(phase)).to(basis.dtype) * basis
            half = span // 2
            sums = [(y_b[:, half:].sum(-1), r_b[half:].sum()), (y_b[:, :half].sum(-1), r_b[:half].sum())]
        else:
            col = torch.arange(span, device=self.device)[None, :]
            last = col >= span - window[:, None]
            before = (col >= span - 2 * window[:, None]) & ~last
            phase = w[:, None] * t[None, :]
            basis = torch.complex(torch.cos(phase), -torch.sin(phase))
            y_b = y.to(basis.dtype) * basis
            r_b = (amp * torch.sin(phase)).to(basis.dtype) * basis
            sums = [((y_b * m).sum(-1), (r_b * m).sum(-1)) for m in (last, before)]
        (l1, t1), (l0, t0) = [(y_h / (r_h - y_h), y_h / r_h) for y_h, r_h in sums]
        return l1, t1, l0, t0

    def _bucketed(
        self, k: torch.Tensor, f: torch.Tensor, window: torch.Tensor, periods: int, state: SimState | None = None
    ) -> tuple[Readings, SimState]:
        """``_harmonics`` of a batch whose size varies from call to call (extensions, refinement): with a compiled
        simulator the rows are padded (the last one repeated) to :func:`padded_size`, so that a few compiled
        batch sizes serve every call instead of one compilation per size (and eager past the recompile limit)."""
        n = k.shape[0]
        if not self.sweep.compile or n == 0:
            return self._harmonics(k, f, window, periods, state)
        idx = padding_index(n, padded_size(n), k.device)
        read, end = self._harmonics(k[idx], f[idx], window[idx], periods, None if state is None else state.rows(idx))
        return read.rows(slice(0, n)), end.rows(slice(0, n))

    def _settled(
        self, k: torch.Tensor, f: torch.Tensor, window: torch.Tensor, periods: int, bucket: bool = False
    ) -> Readings:
        """``_harmonics`` with the rows that have not settled simulated on to twice as long (the module
        docstring); ``settled`` (R,) bool set. ``bucket``: the first simulation's batch size varies too."""
        read, state = (self._bucketed if bucket else self._harmonics)(k, f, window, periods)
        settled = read.change <= self.sweep.tolerance
        todo = torch.nonzero(~settled)[:, 0]
        state = state.rows(todo)  # the end states of the rows in todo, in its order
        for _ in range(int(self.sweep.max_extensions)):
            if todo.numel() == 0:
                break
            # on from where the rows stopped to twice the time: the trajectory of a run that long from rest
            self.extensions += int(todo.numel())
            again, state = self._bucketed(k[todo], f[todo], window[todo], periods, state)
            periods *= 2
            read.put(todo, again)
            ok = again.change <= self.sweep.tolerance
            settled[todo] = ok
            state = state.rows(torch.nonzero(~ok)[:, 0])
            todo = todo[~ok]
        self.unsettled += int(todo.numel())
        read.settled = settled
        return read

    def measure(self, faults: torch.Tensor) -> LoopResponse:
        """Frequency response of every fault vector on the grid.

        Args:
            faults: (B, 8) fault vectors in [0, 1].
        Returns:
            The responses at the F test frequencies.
        """
        k = as_fault_tensor(faults, torch.float64, self.device)
        b = k.shape[0]
        cols: dict[int, list[torch.Tensor]] = {}
        for grp in self.groups:
            periods = max(self.plan[i][2] for i in grp)
            f = torch.tensor([self.plan[i][0] for i in grp], dtype=torch.float64, device=self.device)
            window = torch.tensor([self.plan[i][1] for i in grp], device=self.device)
            # rows g * B + b: frequency grp[g], fault vector b
            read = self._settled(k.repeat(len(grp), 1), f.repeat_interleave(b), window.repeat_interleave(b), periods)
            for g, i in enumerate(grp):
                cols.setdefault(i, [x[g * b : (g + 1) * b] for x in read.columns])
        return LoopResponse(
            self.frequencies.to(self.device),
            *(torch.stack([cols[i][j] for i in range(len(self.plan))], -1) for j in range(5)),
        )

    def margins_of(self, r: LoopResponse) -> Margins:
        """Margins of ``r``, a response this sweep measured, read with the sweep's no-response floor (every swept
        loop's margins go through here, so that no caller reads a reading stuck in dry friction as a response)."""
        return margins(r.frequencies, r.open_loop, r.closed_loop, self.sweep.no_response_db)

    def read(self, faults: torch.Tensor) -> LoopResponse:
        """The response phi_a reads: :meth:`measure` on the grid, then :meth:`refine` (``sweep.refine`` rounds)."""
        return self.refine(faults, self.measure(faults))

    def refine(self, faults: torch.Tensor, r: LoopResponse) -> LoopResponse:
        """``r`` after ``sweep.refine`` rounds (module docstring).

        Args:
            faults: (B, 8) the fault vectors ``r`` was measured for.
            r: their response, on the grid or already refined.
        Returns:
            ``r`` with, each round, every vector measured again at its interpolated gain crossover, phase
            crossover and bandwidth (where measurable), the points inserted in frequency order: (B, F + 3)
            frequencies per round.
        """
        k = as_fault_tensor(faults, torch.float64, self.device)
        for _ in range(int(self.sweep.refine)):
            r = self._refine_once(k, r)
        return r

    def _refine_once(self, k: torch.Tensor, r: LoopResponse) -> LoopResponse:
        b = k.shape[0]
        m = self.margins_of(r)
        freqs = r.frequencies.expand(b, -1) if r.frequencies.ndim == 1 else r.frequencies
        old = (r.open_loop, r.closed_loop, r.settled, r.open_loop_before, r.closed_loop_before)
        if any(x is None for x in old):
            raise ValueError("refine needs a response measured by measure() (settled and before-window readings)")
        new: list[list[torch.Tensor]] = [[freqs], *([x] for x in old)]
        for target in (m.crossover_hz, m.phase_crossover_hz, m.bandwidth_hz):
            # vectors without this crossing repeat their first grid point (a zero-width interval adds nothing)
            cols = [x[:, 0].clone() for x in (freqs, *old)]
            rows = torch.nonzero(torch.isfinite(target))[:, 0]
            tests = [self._test(float(f)) for f in target[rows]]
            # each row for its own test's duration rounded up to a power of two control periods, with the rows of
            # that duration: a reading that depends on the other rows of the batch (the longest test's duration for
            # all) would make a label depend on the batch (the grid's groups are fixed by the plan)
            spans = torch.tensor([1 << (x[2] - 1).bit_length() for x in tests], dtype=torch.long)
            for span in torch.unique(spans).tolist():
                part = torch.nonzero(spans == span)[:, 0]
                f_t = torch.tensor([tests[i][0] for i in part], dtype=torch.float64, device=self.device)
                window = torch.tensor([tests[i][1] for i in part], device=self.device)
                read = self._settled(k[rows[part]], f_t, window, int(span), bucket=True)
                for col, value in zip(cols, (f_t, *read.columns), strict=True):
                    col[rows[part]] = value
            for lst, col in zip(new, cols, strict=True):
                lst.append(col[:, None])
        f_all = torch.cat(new[0], -1)
        order = torch.argsort(f_all, dim=-1, stable=True)
        return LoopResponse(*(torch.cat(lst, -1).gather(-1, order) for lst in new))
