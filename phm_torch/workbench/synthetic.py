"""Synthetic measurements with hidden effects, for tests, the benchmark and the demo.

Several cases run in one batched simulator call: case i enables only its own effects (the other effects
of the union at strength 0), with its own fault vector and datasheet multipliers; Gaussian noise is then
added to the current and the position.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field

import torch

from ..effects import EFFECTS
from ..io import Measurement
from ..params import ActuatorParams
from ..sensor_noise import add_sensor_noise
from ..simulator import EMASimulator
from .parameters import effect_defaults

CSV_CHANNELS = ("position", "current", "speed", "motor_angle")


@dataclass
class Case:
    """One synthetic measurement.

    Attributes:
        effects: hidden effects {name: {param: value}} (missing values: defaults).
        noise: {channel: std} of the Gaussian noise added (``current`` [A], ``position`` [rad]).
        faults: fault vector (default nominal).  scales: datasheet multipliers {field: value}.
        seed: noise seed.
    """

    effects: Mapping[str, Mapping[str, float]] = field(default_factory=dict)
    noise: Mapping[str, float] = field(default_factory=lambda: {"current": 0.02, "position": 2e-5})
    faults: Sequence[float] | None = None
    scales: Mapping[str, float] = field(default_factory=dict)
    seed: int = 0


def synthesize(
    params: ActuatorParams, cases: Sequence[Case], command: torch.Tensor | object, duration: float, fidelity: str = "lf"
) -> list[Measurement]:
    """Simulate every case in one call and return noisy measurements.

    Args:
        command: a callable of time (e.g. ``Chirp``) or a tensor (n,) on the acquisition grid [rad].
        duration: [s].
    """
    names = sorted({n for c in cases for n in c.effects})
    spec: dict[str, dict[str, torch.Tensor]] = {}
    for name in names:
        cls = EFFECTS[name]
        cols: dict[str, list[float]] = {k: [] for k in cls.PARAMS}
        for c in cases:
            vals = effect_defaults(name, c.effects.get(name), params)
            for k in cls.PARAMS:
                off = name not in c.effects and k in cls.STRENGTH
                cols[k].append(0.0 if off else vals[k])
        spec[name] = {k: torch.tensor(v, dtype=torch.float64) for k, v in cols.items()}
    faults = torch.tensor(
        [list(c.faults) if c.faults is not None else list(params.nominal_faults) for c in cases], dtype=torch.float64
    )
    fields_ = sorted({f for c in cases for f in c.scales})
    scales = {f: torch.tensor([float(c.scales.get(f, 1.0)) for c in cases], dtype=torch.float64) for f in fields_}
    sim = EMASimulator(params, fidelity, effects=spec)
    with torch.no_grad():
        sig = sim.run(faults, command, duration, scales=scales, channels=list(CSV_CHANNELS))
    out = []
    for i, c in enumerate(cases):
        clean = {k: sig[k][i].clone() for k in (*CSV_CHANNELS, "command")}
        chans = add_sensor_noise(clean, {k: float(v) for k, v in c.noise.items()}, int(c.seed))
        np_ = {k: v.numpy() for k, v in chans.items()}
        out.append(
            Measurement(
                sig.time.numpy().copy(),
                np_["command"],
                np_["position"],
                np_["current"],
                {k: np_[k] for k in ("speed", "motor_angle")},
                float(params.sample_rate),
            )
        )
    return out
