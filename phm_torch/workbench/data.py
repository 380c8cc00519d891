"""Measurement records for the workbench: read a measurement CSV, check it fits the model, hold it as tensors.

The model starts at rest at zero position at t = 0 and is driven by the measured command, so a record is
usable only if it is sampled at the actuator's acquisition rate, starts at rest near zero and commands
positions inside the end stops. Every problem is a :class:`ValueError` naming the file and the field.
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

from ..io import Measurement, read_measurement
from ..params import ActuatorParams

# Channels the workbench can compare with a simulation (the simulator's names).
COMPARABLE = ("position", "current", "speed", "motor_angle", "user_angle", "ia", "ib", "ic")
MIN_DURATION = 0.01  # [s] shortest record worth fitting (diagnostic windows need a few ms)
START_TOLERANCE = 0.05  # initial position allowed, as a fraction of the largest |command|
START_SAMPLES = 20  # samples averaged to read the initial position (averages the noise out)


@dataclass
class Record:
    """One validated measurement on the model's time grid.

    Attributes:
        name: label (file stem).  path: source file or ``None``.
        time: (n,) [s], starting at 0 (the file's start time ``t0`` is subtracted).
        command: (n,) [rad, user side].  measured: {channel: (n,)} in the channel's unit.
        sample_rate: [Hz].  t0: start time of the file [s].  extra: the file's other channels (not compared).
    """

    name: str
    time: torch.Tensor
    command: torch.Tensor
    measured: dict[str, torch.Tensor]
    sample_rate: float
    path: Path | None = None
    t0: float = 0.0
    extra: dict[str, torch.Tensor] = field(default_factory=dict)

    def __len__(self) -> int:
        return int(self.time.numel())

    @property
    def duration(self) -> float:
        """Simulated duration [s]: (n - 1) / f_s."""
        return (len(self) - 1) / self.sample_rate

    def channel_range(self, channel: str) -> float:
        """max - min of a measured channel, the NRMSE normaliser."""
        x = self.measured[channel]
        return float(x.max() - x.min())


def record_from_measurement(
    m: Measurement,
    params: ActuatorParams,
    channels: Sequence[str],
    name: str = "record",
    path: Path | None = None,
    dtype: torch.dtype = torch.float64,
) -> Record:
    """Check that a measurement can be compared with the model and convert it to a :class:`Record`.

    Args:
        m: the measurement (e.g. from :func:`phm_torch.io.read_measurement`).
        params: the actuator (sample rate, end stops).
        channels: channels to compare (must be columns of the file).
        name: label used in reports; path: the source file, for messages.

    Raises:
        ValueError: naming the file and the column: another sample rate, a missing channel, too short,
            a constant channel, a command beyond the end stops, or a record not starting at rest near 0.
    """
    where = str(path) if path is not None else name
    rate = float(m.sample_rate)
    if abs(rate - params.sample_rate) > 1e-4 * params.sample_rate:
        raise ValueError(
            f"{where}: sample rate {rate:.6g} Hz differs from the model's acquisition rate "
            f"actuator.sample_rate={params.sample_rate:.6g} Hz (read with resample=true to interpolate)"
        )
    unknown = [c for c in channels if c not in COMPARABLE]
    if unknown:
        raise ValueError(f"channels: {unknown} cannot be compared with a simulation; choose from {list(COMPARABLE)}")
    missing = [c for c in channels if c not in m.channels]
    if missing:
        raise ValueError(
            f"{where}: channel(s) {missing} requested by channels= are not in the file; "
            f"columns: {['time', *m.channels]}"
        )
    n = len(m)
    if (n - 1) / rate < MIN_DURATION:
        raise ValueError(f"{where}: {n} samples ({(n - 1) / rate:.4g} s) is too short; need at least {MIN_DURATION} s")
    for c in channels:
        if float(np.ptp(m[c])) <= 0.0:
            raise ValueError(f"{where}: column {c!r} is constant ({m[c][0]!r}); nothing to compare")
    cmd = m.command
    i_max = int(np.argmax(np.abs(cmd)))
    if abs(cmd[i_max]) > params.end_stop_angle:
        raise ValueError(
            f"{where}: column 'command' = {cmd[i_max]:.6g} rad at line {i_max + 2} (t = "
            f"{m.time[i_max]:.6g} s) is beyond the model's end stops "
            f"actuator.end_stop_angle=±{params.end_stop_angle:g} rad"
        )
    amp = float(np.abs(cmd).max())
    start = float(np.mean(m.position[:START_SAMPLES]))
    tol = START_TOLERANCE * amp if amp > 0 else 1e-4
    if abs(start) > tol:
        raise ValueError(
            f"{where}: column 'position' starts at {start:.6g} rad (mean of the first {START_SAMPLES} "
            f"samples) but the model starts at rest at 0 rad (tolerance {tol:.3g} rad); the record "
            "must begin with the actuator at rest at zero"
        )
    t = torch.as_tensor(m.time - m.time[0], dtype=dtype)
    to_t = {c: torch.as_tensor(m[c], dtype=dtype) for c in channels}
    extra = {c: torch.as_tensor(v, dtype=dtype) for c, v in m.channels.items() if c not in to_t and c != "command"}
    return Record(name, t, torch.as_tensor(cmd, dtype=dtype), to_t, rate, path, float(m.time[0]), extra)


def load_records(
    paths: str | os.PathLike | Sequence[str | os.PathLike],
    params: ActuatorParams,
    channels: Sequence[str],
    resample: bool = False,
) -> list[Record]:
    """Read and validate one or several measurement CSV files.

    Args:
        paths: a path or a list of paths.
        params: the actuator the records are compared with.
        channels: channels to compare, e.g. ``("position", "current")``.
        resample: interpolate a file sampled at another rate onto the actuator's rate instead of failing.

    Raises:
        ValueError: no file given, or any problem of :func:`read_measurement` / :func:`record_from_measurement`.
    """
    if isinstance(paths, (str, os.PathLike)):
        paths = [paths]
    paths = list(paths)
    if not paths:
        raise ValueError("measurements: no file given (measurements=PATH.csv or measurements=[A.csv,B.csv])")
    records, names = [], set()
    for p in paths:
        if not isinstance(p, (str, os.PathLike)) or not str(p).strip():
            raise ValueError(f"measurements: expected a CSV path, got {p!r}")
        path = Path(p).expanduser()
        m = read_measurement(path, expected_rate=params.sample_rate, resample=resample)
        name = path.stem
        while name in names:
            name += "_"
        names.add(name)
        records.append(record_from_measurement(m, params, channels, name, path))
    return records
