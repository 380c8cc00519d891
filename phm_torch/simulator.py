"""The EMA simulator: one init/step interface shared by every fidelity.

The fidelity is only the motor model (``BLDCMotor`` = HF test bench, ``DCMotor`` = LF), reached through the
``physics.motor.Motor`` protocol; control, mechanics, sensors, faults, effects and the energy balance
(``physics.energy``) are the same code. ``step`` advances one PWM/control period in ``motor.substeps``
substeps and returns the acquisition samples that fall inside it.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Iterator, Mapping, Sequence
from dataclasses import dataclass, field

import torch

from .command import time_grid
from .effects import Effect, EffectContext, build_effects
from .faults import as_fault_tensor
from .params import ActuatorParams
from .physics import energy as energy_balance
from .physics.controller import ControlState, controller_step
from .physics.mechanics import MechState, mechanics_step
from .physics.motor import MOTORS, default_substeps
from .physics.sensors import ButterworthFilter, lvdt_step
from .plant import Plant, build_plant
from .sim_state import SimState

# Channels every fidelity records; a motor adds its own (``Motor.channels``).
SHARED_CHANNELS = ("position", "current", "speed", "motor_angle", "user_angle")
# Every simulator shares the code of ``_substep``/``step``, and dynamo guards each compiled graph on the
# instance (fidelity, effects): past its default recompile limit of 8, a process that builds more compiled
# simulators (one per effect set, e.g. scripts/fdi_model_mismatch.py) would silently run the rest eager.
RECOMPILE_LIMIT = 64


@dataclass
class Signals:
    """Simulated acquisition, every channel (B, n) on the uniform grid ``time`` (n,) [s].

    Channels: ``command`` [rad], ``position`` (LVDT) [rad], ``current`` (filtered envelope) [A],
    ``speed`` (motor) [rad/s], ``motor_angle`` [rad], ``user_angle`` [rad]; HF adds ``ia``, ``ib``,
    ``ic`` [A] (unfiltered phase currents).
    """

    time: torch.Tensor
    channels: dict[str, torch.Tensor]
    faults: torch.Tensor
    fidelity: str
    energy: dict[str, torch.Tensor] | None = None
    meta: dict = field(default_factory=dict)
    state: SimState | None = None  # where the simulation ended: ``run(..., state=...)`` continues from it

    def __getitem__(self, name: str) -> torch.Tensor:
        if name == "time":
            return self.time
        if name not in self.channels:
            raise KeyError(f"no channel {name!r}; available: {sorted(self.channels)}")
        return self.channels[name]


class EMASimulator:
    """Batched EMA simulator.

    Args:
        params: actuator datasheet.
        fidelity: a motor model of ``physics.motor.MOTORS``: ``"hf"`` or ``"lf"``.
        effects: list of effects or a ``{name: {param: value}}`` mapping.
        substeps: substeps per PWM period (default the motor's ``default_substeps``: 10 for HF -> 10 us,
            2 for LF -> 50 us; raised to a multiple of the samples per period, ``physics.motor.default_substeps``).
        dtype, device: tensor placement; float64 by default (the backlash is ~1e-3 of the stroke).
        compile: fuse with ``torch.compile`` (same equations, equal to eager within 1e-9): each HF
            substep, or each whole LF period; several times faster for large batches after a one-off
            compilation (~15-50 s) per batch size.
    """

    def __init__(
        self,
        params: ActuatorParams,
        fidelity: str = "hf",
        effects: Iterable[Effect] | Mapping[str, Mapping] | None = None,
        substeps: int | None = None,
        dtype: torch.dtype = torch.float64,
        device: str | torch.device = "cpu",
        compile: bool = False,
    ):
        if fidelity not in MOTORS:
            raise ValueError(f"fidelity must be one of {sorted(MOTORS)}, got {fidelity!r}")
        self.params = params
        self.fidelity = fidelity
        motor = MOTORS[fidelity]
        self.motor = motor(substeps or default_substeps(motor, params.pwm_frequency, params.sample_rate))
        # copies on the simulation dtype/device (grads kept): the caller's effects are left as given
        given = build_effects(effects, params) if effects is None or isinstance(effects, Mapping) else effects
        self.effects = [eff.to(dtype, device) for eff in given]
        self.dtype, self.device = dtype, torch.device(device)
        self.period = params.control_period
        self.h = self.period / self.motor.substeps
        per_sample = self.motor.substeps * params.pwm_frequency / params.sample_rate
        if abs(per_sample - round(per_sample)) > 1e-9 or round(per_sample) < 1:
            raise ValueError(
                f"{fidelity}.substeps={self.motor.substeps}: the acquisition period "
                f"1/{params.sample_rate} s must be a whole number of substeps of {self.h:.3g} s"
            )
        self.substeps_per_sample = round(per_sample)
        # a sample rate below the PWM frequency samples every m-th period (at its start): step() offers the
        # period's first substep, run() keeps it from every m-th period only
        self.periods_per_sample = max(1, self.substeps_per_sample // self.motor.substeps)
        self.filter = ButterworthFilter(params.filter_cutoff, self.h, dtype, self.device)
        self._offsets = [torch.tensor(j * self.h, dtype=dtype, device=self.device) for j in range(self.motor.substeps)]
        self.compiled = compile
        # What one compiled graph covers (a whole period or one substep) is the motor's to say.
        whole_period = compile and self.motor.compile_whole_period
        if compile:
            torch._dynamo.config.recompile_limit = max(torch._dynamo.config.recompile_limit, RECOMPILE_LIMIT)
        self._substep_fn = (
            torch.compile(self._substep, dynamic=False) if compile and not whole_period else self._substep
        )
        self._step_fn = torch.compile(self.step, dynamic=False) if whole_period else self.step

    # ---- init / step -------------------------------------------------------------------------
    def init(self, faults, scales: Mapping[str, torch.Tensor] | None = None, energy: bool = False) -> SimState:
        """Actuator at rest at zero position, controller integrators empty."""
        k = as_fault_tensor(faults, self.dtype, self.device)
        plant = build_plant(self.params, k, scales)
        for eff in self.effects:
            plant = eff.modify_plant(plant)
            if not isinstance(plant, Plant):
                raise TypeError(
                    f"effects.{eff.name}.modify_plant must return the new Plant "
                    f"(dataclasses.replace(plant, ...)), got {type(plant).__name__}"
                )
        b = k.shape[0]
        z = torch.zeros(b, dtype=self.dtype, device=self.device)
        acc = energy_balance.empty_accounts(b, self.dtype, self.device) if energy else None
        return SimState(
            plant,
            MechState.zeros(b, self.dtype, self.device),
            ControlState.zeros(b, self.dtype, self.device),
            self.motor.init_state(plant),
            z.clone(),
            (z.clone(), z.clone()),
            z.clone(),
            torch.zeros((), dtype=self.dtype, device=self.device),
            acc,
        )

    def step(self, state: SimState, command: torch.Tensor) -> tuple[SimState, list[dict[str, torch.Tensor]]]:
        """Advance one control period.

        Args:
            command: position command sampled at this period's start [rad] (B,) or scalar.
        Returns:
            The new state and the acquisition samples taken at the substep boundaries of this period
            that fall on the acquisition grid (raw: the filter output, before any noise); at a sample rate below
            the PWM frequency, the period's start, on the grid for one period in ``periods_per_sample``.
        """
        plant = state.plant
        i_fb = self.motor.feedback_current(state.elec, state.mech.theta_m, plant)
        ctrl, _ = controller_step(state.ctrl, command, state.lvdt, state.mech.omega_m, i_fb, plant, self.period)
        duty = state.ctrl.duty  # computed one period ago (computation delay)
        mech, elec, lvdt, filt, env = state.mech, state.elec, state.lvdt, state.filt, state.envelope
        t_start = state.time
        samples = []
        for j in range(self.motor.substeps):
            if j % self.substeps_per_sample == 0:
                samples.append(self._sample(mech, elec, lvdt, filt))
            mech, elec, lvdt, filt, env = self._substep_fn(
                plant, mech, elec, lvdt, filt, env, duty, self._offsets[j], t_start + self._offsets[j], state.energy
            )
        return SimState(plant, mech, ctrl, elec, lvdt, filt, env, t_start + self.period, state.energy), samples

    def _substep(
        self,
        plant: Plant,
        mech: MechState,
        elec: torch.Tensor,
        lvdt: torch.Tensor,
        filt: tuple,
        env: torch.Tensor,
        duty: torch.Tensor,
        offset: torch.Tensor,
        time: torch.Tensor,
        energy: dict[str, torch.Tensor] | None,
    ):
        """One substep of motor, effects, mechanics and sensors (the unit that ``compile`` fuses)."""
        eff_motor = eff_fric = eff_break = eff_load = 0.0
        emf_scale, d = 1.0, duty
        if self.effects:
            ctx = EffectContext(
                time,
                mech.theta_m,
                mech.omega_m,
                mech.theta_u,
                mech.omega_u,
                self.motor.feedback_current(elec, mech.theta_m, plant),
                plant,
            )
            for eff in self.effects:
                emf_scale = emf_scale * eff.emf_scale(ctx)
                d = d + eff.voltage_error(ctx) / plant.supply_voltage
                eff_motor = eff_motor + eff.motor_torque(ctx)
                eff_fric = eff_fric + eff.friction_torque(ctx)
                eff_break = eff_break + eff.breakaway_torque(ctx)
                eff_load = eff_load + eff.load_torque(ctx)
            d = d.clamp(-1.0, 1.0)
        elec_new, torque, env_new, extra = self.motor.step(
            elec, d, offset, mech.theta_m, mech.omega_m, emf_scale, plant, self.h, self.period
        )
        filt = self.filter.step(filt, 0.5 * (env + env_new))
        load = torch.zeros_like(torque) + eff_load
        mech_new, torques = mechanics_step(
            mech,
            torque + eff_motor,
            load,
            plant.coulomb_friction + eff_fric,
            plant.static_friction + eff_break,
            plant,
            self.h,
        )
        if energy is not None:
            energy_balance.accumulate(
                energy,
                self.motor,
                self.h,
                extra["power_in"],
                elec,
                elec_new,
                mech,
                mech_new,
                torques,
                eff_motor,
                load,
                plant,
            )
        # Mid-step user angle: the exact lag of a linearly varying input to second order in h.
        lvdt = lvdt_step(lvdt, 0.5 * (mech.theta_u + mech_new.theta_u), plant.lvdt_time_constant, self.h)
        return mech_new, elec_new, lvdt, filt, env_new

    def _sample(
        self, mech: MechState, elec: torch.Tensor, lvdt: torch.Tensor, filt: tuple[torch.Tensor, ...]
    ) -> dict[str, torch.Tensor]:
        return {
            "position": lvdt,
            "current": filt[0],
            "speed": mech.omega_m,
            "motor_angle": mech.theta_m,
            "user_angle": mech.theta_u,
            **self.motor.sample(elec),
        }

    # ---- whole runs --------------------------------------------------------------------------
    def run(
        self,
        faults,
        command: Callable[[torch.Tensor], torch.Tensor] | torch.Tensor,
        duration: float,
        scales: Mapping[str, torch.Tensor] | None = None,
        energy: bool = False,
        channels: Sequence[str] | None = None,
        out_dtype: torch.dtype | None = None,
        state: SimState | None = None,
    ) -> Signals:
        """Simulate ``duration`` seconds from rest, or on from ``state``.

        Args:
            faults: (B, 8) or (8,) fault vectors in [0, 1].
            command: a callable of time [s] -> [rad] (e.g. ``Chirp``), or a tensor (n,) / (B, n) of the
                command on the acquisition grid (linearly interpolated at the control instants).
            duration: [s]; the grid has round(duration * f_s) + 1 samples.
            scales: multipliers on nominal parameters (see ``build_plant``), may require grad.
            energy: also accumulate the energy terms of the power balance (``Signals.energy``).
            channels: channels to keep (default all); fewer channels, less memory.
            out_dtype: dtype of the stored channels (default the simulation dtype).
            state: continue from this state (``Signals.state`` of an earlier run of ``faults``, or its
                :meth:`~phm_torch.sim_state.SimState.rows`) instead of from rest: the grid and the command's time
                start at its time, and ``duration`` more seconds are simulated, exactly as one longer run would
                have. The plant (``scales``) and the energy accounts are the state's (passing either is an error);
                the accounts go on accumulating in the state's own dict.
        Returns:
            The acquisition, with the state it ended in (``Signals.state``).
        """
        p = self.params
        n_periods = round(duration * p.pwm_frequency)
        if n_periods < 1 or abs(duration * p.pwm_frequency - n_periods) > 1e-6:
            raise ValueError(
                f"duration must be a positive whole number of control periods "
                f"(1/{p.pwm_frequency:g} s), got {duration!r}"
            )
        # control periods already simulated: times are counted from rest, as in one longer run
        start = 0 if state is None else round(float(state.time) * p.pwm_frequency)
        if state is not None and (scales is not None or energy):
            raise ValueError("scales/energy: a continued run (state given) keeps the state's plant and accounts")
        first = start * p.sample_rate / p.pwm_frequency  # the acquisition samples already taken
        if abs(first - round(first)) > 1e-9 or start % self.periods_per_sample:
            raise ValueError(
                f"state: at {start} control periods, between two acquisition samples; continue on the grid"
            )
        grid = time_grid(duration, p.sample_rate, self.dtype, self.device)
        if start:
            grid = (torch.arange(grid.numel(), dtype=self.dtype, device=self.device) + round(first)) / p.sample_rate
        t_ctrl = torch.arange(start, start + n_periods, dtype=self.dtype, device=self.device) * self.period
        if callable(command):
            cmd_grid, cmd_ctrl = command(grid), command(t_ctrl)
        else:
            cmd_grid = torch.as_tensor(command, dtype=self.dtype, device=self.device)
            if cmd_grid.shape[-1] != grid.numel():
                raise ValueError(
                    f"command has {cmd_grid.shape[-1]} samples, the grid of {duration} s at "
                    f"{p.sample_rate} Hz has {grid.numel()}"
                )
            if not torch.isfinite(cmd_grid).all():
                raise ValueError("command contains NaN or inf")
            cmd_ctrl = _interp(t_ctrl, grid, cmd_grid)
        k_t = as_fault_tensor(faults, self.dtype, self.device)
        if state is None:
            state = self.init(k_t, scales, energy)
        elif state.plant.batch != k_t.shape[0]:
            raise ValueError(f"state: {state.plant.batch} actuators, faults: {k_t.shape[0]}; continue the same rows")
        b, n = state.plant.batch, grid.numel()
        available = SHARED_CHANNELS + self.motor.channels
        keep = list(channels) if channels is not None else list(available)
        unknown = sorted(set(keep) - set(available) - {"command"})
        if unknown:
            raise ValueError(f"channels: unknown {unknown}; available: {list(available)}")
        keep = [c for c in keep if c != "command"]
        dtype = out_dtype or self.dtype
        grad = torch.is_grad_enabled() and any(t.requires_grad for t in state.plant.to_dict().values())
        # Without autograd, write into preallocated buffers: no list of 10^4 tensors, no stacking copy.
        bufs = None if grad else {c: torch.empty(b, n, dtype=dtype, device=self.device) for c in keep}
        records: list[dict[str, torch.Tensor]] = []
        idx = 0

        def store(sample: dict[str, torch.Tensor]) -> None:
            nonlocal idx
            if bufs is None:
                records.append({c: sample[c] for c in keep})
            else:
                for c in keep:
                    bufs[c][:, idx] = sample[c]
            idx += 1

        for k in range(n_periods):
            state, samples = self._step_fn(state, cmd_ctrl[..., k])
            if k % self.periods_per_sample == 0:
                for smp in samples:
                    store(smp)
        store(self._sample(state.mech, state.elec, state.lvdt, state.filt))
        if state.energy is not None:
            state.energy["stored"] = energy_balance.stored_energy(self.motor, state.plant, state.mech, state.elec)
        if bufs is None:
            out = {c: torch.stack([r[c] for r in records], dim=-1).to(dtype) for c in keep}
        else:
            out = bufs
        out["command"] = cmd_grid.to(dtype).expand(b, -1)  # (n,) or (B, n) -> (B, n)
        return Signals(
            grid,
            out,
            k_t,
            self.fidelity,
            state.energy,
            {"substeps": self.motor.substeps, "effects": [repr(e) for e in self.effects]},
            state,
        )

    def iter_chunks(self, faults, command, duration: float, chunk_size: int, **kwargs) -> Iterator[Signals]:
        """Simulate a large batch ``chunk_size`` samples at a time, yielding each chunk's signals.

        Memory stays bounded by one chunk whatever the batch size; results equal those of one call.
        """
        if chunk_size < 1:
            raise ValueError(f"chunk_size must be >= 1, got {chunk_size}")
        k = as_fault_tensor(faults, self.dtype, self.device)
        for start in range(0, k.shape[0], chunk_size):
            yield self.run(k[start : start + chunk_size], command, duration, **kwargs)


def _interp(x: torch.Tensor, xp: torch.Tensor, fp: torch.Tensor) -> torch.Tensor:
    """Linear interpolation of fp (..., n) given on the uniform grid xp (n,) at points x (m,)."""
    pos = (x - xp[0]) / (xp[1] - xp[0])
    i0 = pos.floor().long().clamp(0, xp.numel() - 2)
    w = (pos - i0.to(pos.dtype)).clamp(0.0, 1.0)
    return fp[..., i0] * (1 - w) + fp[..., i0 + 1] * w


def simulate(
    params: ActuatorParams,
    faults,
    command,
    duration: float | None = None,
    fidelity: str = "hf",
    effects: Iterable[Effect] | Mapping[str, Mapping] | None = None,
    **kwargs,
) -> Signals:
    """Convenience wrapper: ``EMASimulator(params, fidelity, effects, **kwargs).run(faults, command, duration)``."""
    duration = duration if duration is not None else getattr(command, "duration", None)
    if duration is None:
        raise ValueError("duration is required when the command has no 'duration'")
    return EMASimulator(params, fidelity, effects, **kwargs).run(faults, command, duration)


__all__: Sequence[str] = ("MOTORS", "EMASimulator", "Signals", "SimState", "simulate")
