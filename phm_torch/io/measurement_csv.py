"""Measurement CSV files: the exchange format between the test bench (or the simulator) and the tools.

Format (one file = one acquisition):

* a header row naming the columns, then one row per sample, comma separated;
* uniform sampling; the columns ``time`` [s], ``command`` [rad, user side; m for a linear actuator], ``position``
  [rad, LVDT; m]
  and ``current`` [A, filtered envelope of the phase currents] are required, in any order;
* any further numeric columns are optional channels, e.g. ``ia``, ``ib``, ``ic`` [A], ``speed``
  [rad/s, motor], ``motor_angle`` [rad].
* as benches write them: the known columns' names in any case, with a unit in brackets or parentheses
  (``Time [ms]``, ``current (mA)``, ``position [deg]``, ``command [mm]``: :data:`UNIT_SCALES`, converted to the units
  above on reading;
  an unknown unit is an error naming it), comma, semicolon or tab separated (with a semicolon or a tab, decimal
  commas are read too).

Reading validates everything and raises :class:`ValueError` naming the file, the column and the line
(line 1 is the header) of the first problem found.
"""

from __future__ import annotations

import csv
import math
import os
import re
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from .atomic import atomic_open

REQUIRED = ("time", "command", "position", "current")
UNITS = {
    "time": "s",
    "command": "rad",
    "position": "rad",
    "current": "A",
    "ia": "A",
    "ib": "A",
    "ic": "A",
    "speed": "rad/s",
    "motor_angle": "rad",
    "user_angle": "rad",
}

# Units a known column may carry in its header ("current [mA]"): the factor to this module's unit (UNITS)
_ANGLE = {"rad": 1.0, "mrad": 1e-3, "deg": math.pi / 180.0, "°": math.pi / 180.0}
# the user side's coordinate: an angle [rad], or a length [m] on a linear actuator (docs/own_actuator.md)
_USER = {**_ANGLE, "m": 1.0, "mm": 1e-3, "um": 1e-6, "µm": 1e-6}
_CURRENT = {"a": 1.0, "ma": 1e-3}
UNIT_SCALES = {
    "time": {"s": 1.0, "ms": 1e-3, "us": 1e-6, "µs": 1e-6},
    "command": _USER,
    "position": _USER,
    "motor_angle": _ANGLE,
    "user_angle": _USER,
    "current": _CURRENT,
    "ia": _CURRENT,
    "ib": _CURRENT,
    "ic": _CURRENT,
    "speed": {"rad/s": 1.0, "rpm": 2.0 * math.pi / 60.0},
}
_HEADER = re.compile(r"^\s*(?P<name>[^\[\(]*?)\s*(?:[\[\(]\s*(?P<unit>[^\]\)]*?)\s*[\]\)])?\s*$")

# Relative tolerances: a time step may differ from the median step by this fraction of it (timestamps
# written with a few decimals are quantised); the sample rate may differ from the expected one by this.
TIME_STEP_TOLERANCE = 0.05
RATE_TOLERANCE = 1e-4


@dataclass
class Measurement:
    """One acquisition on a uniform grid; every channel is a float64 array (n,).

    Attributes:
        time: [s].  command: [rad, user side].  position: LVDT [rad].  current: filtered envelope [A].
        extra: further channels by name (``ia``, ``ib``, ``ic``, ``speed``, ``motor_angle``...).
        sample_rate: [Hz].
        source_rate: the file's own rate [Hz] when the data were resampled on reading, else ``None``.
    """

    time: np.ndarray
    command: np.ndarray
    position: np.ndarray
    current: np.ndarray
    extra: dict[str, np.ndarray] = field(default_factory=dict)
    sample_rate: float = float("nan")
    source_rate: float | None = None

    def __len__(self) -> int:
        return int(self.time.shape[0])

    @property
    def channels(self) -> dict[str, np.ndarray]:
        """Every channel except time: command, position, current, then the extras."""
        return {"command": self.command, "position": self.position, "current": self.current, **self.extra}

    def __getitem__(self, name: str) -> np.ndarray:
        if name == "time":
            return self.time
        chans = self.channels
        if name not in chans:
            raise KeyError(f"no channel {name!r}; available: {['time', *chans]}")
        return chans[name]


# ---- writing --------------------------------------------------------------------------------------
def _to_numpy(value: Any) -> np.ndarray:
    if hasattr(value, "detach"):  # torch tensor
        value = value.detach().cpu().numpy()
    return np.asarray(value, dtype=np.float64)


def _collect(data: Any, index: int | None) -> dict[str, np.ndarray]:
    """Columns {name: (n,) array} from a Measurement, a ``Signals``-like object or a mapping."""
    if isinstance(data, Measurement):
        return {"time": data.time, **data.channels}
    if hasattr(data, "time") and hasattr(data, "channels"):  # phm_torch.simulator.Signals
        raw = {"time": data.time, **data.channels}
    elif isinstance(data, Mapping):
        raw = dict(data)
    else:
        raise TypeError(f"write_measurement: expected a Measurement, Signals or mapping, got {type(data).__name__}")
    if "time" not in raw:
        raise ValueError("write_measurement: missing column 'time'")
    time = _to_numpy(raw["time"])
    if time.ndim != 1:
        raise ValueError(f"write_measurement: 'time' must be 1-D, got shape {time.shape}")
    cols = {"time": time}
    for name, value in raw.items():
        if name == "time":
            continue
        arr = _to_numpy(value)
        if arr.ndim == 2:
            if index is None:
                if arr.shape[0] != 1:
                    raise ValueError(
                        f"write_measurement: column {name!r} holds a batch of {arr.shape[0]} runs; "
                        "pass index= to choose one"
                    )
                arr = arr[0]
            else:
                if not -arr.shape[0] <= index < arr.shape[0]:
                    raise ValueError(f"write_measurement: index {index} out of range for a batch of {arr.shape[0]}")
                arr = arr[index]
        if arr.ndim != 1:
            raise ValueError(f"write_measurement: column {name!r} must be (n,) or (B, n), got shape {arr.shape}")
        cols[str(name)] = arr
    return cols


def write_measurement(
    path: str | os.PathLike, data: Any, index: int | None = None, columns: Iterable[str] | None = None
) -> Path:
    """Write one acquisition to a measurement CSV, atomically (temporary file + ``os.replace``).

    Args:
        path: destination file; its parent directory is created if needed.
        data: a :class:`Measurement`, a simulator ``Signals`` (channels (B, n)), or a mapping
            {column: (n,) or (B, n) array/tensor} that includes ``time``.
        index: which run of a batch to write (required when the batch holds more than one run).
        columns: optional channels to write besides the required four (default: every channel given),
            written in this order after ``time, command, position, current``.

    Returns:
        The path written.

    Raises:
        ValueError: a required column or a requested one is missing, lengths differ, a value is NaN/inf,
            the time is not strictly increasing, or there are fewer than 2 samples.
    """
    cols = _collect(data, index)
    missing = [c for c in REQUIRED if c not in cols]
    if missing:
        raise ValueError(f"write_measurement: missing required column(s) {missing}")
    extras = [c for c in cols if c not in REQUIRED] if columns is None else [c for c in columns if c not in REQUIRED]
    unknown = [c for c in extras if c not in cols]
    if unknown:
        raise ValueError(f"write_measurement: requested column(s) {unknown} not in the data; available: {list(cols)}")
    names = [*REQUIRED, *extras]
    n = cols["time"].shape[0]
    for name in names:
        if cols[name].shape[0] != n:
            raise ValueError(f"write_measurement: column {name!r} has {cols[name].shape[0]} samples, 'time' has {n}")
        bad = np.flatnonzero(~np.isfinite(cols[name]))
        if bad.size:
            raise ValueError(f"write_measurement: column {name!r} has a non-finite value at sample {bad[0]}")
    if n < 2:
        raise ValueError(f"write_measurement: need at least 2 samples, got {n}")
    if not (np.diff(cols["time"]) > 0).all():
        raise ValueError("write_measurement: 'time' must be strictly increasing")

    path = Path(path)
    table = np.stack([cols[c] for c in names], axis=1).tolist()  # Python floats: repr round-trips exactly
    with atomic_open(path, "w", newline="") as fh:
        writer = csv.writer(fh, lineterminator="\n")
        writer.writerow(names)
        writer.writerows([repr(v) for v in row] for row in table)
    return path


# ---- reading --------------------------------------------------------------------------------------
def _read_header(path: Path, cells: list[str]) -> tuple[list[str], list[float]]:
    """Column names (a known column's in lower case, its unit taken off) and each column's factor to the units of
    :data:`UNITS`, from a header row as written (``Time [ms]``, ``current (mA)``, ``ia``, ``temperature [C]``)."""
    names, scales = [], []
    for cell in cells:
        match = _HEADER.match(cell)
        name, unit = (match["name"], match["unit"]) if match else (cell.strip(), None)
        known = name.lower()
        if known in UNIT_SCALES:
            factors = UNIT_SCALES[known]
            factor = 1.0 if unit is None else factors.get(unit.lower().replace(" ", ""))
            if factor is None:
                raise ValueError(
                    f"{path}: column {cell.strip()!r}: unknown unit {unit!r} for {known!r}; known: {sorted(factors)}"
                )
            names.append(known)
            scales.append(factor)
        else:  # another channel: kept as written
            names.append(cell.strip())
            scales.append(1.0)
    return names, scales


def read_measurement(
    path: str | os.PathLike,
    expected_rate: float | None = None,
    resample: bool = False,
    missing_ok: Iterable[str] = (),
    optional: Iterable[str] = (),
) -> Measurement:
    """Read and validate a measurement CSV.

    Args:
        path: the file.
        expected_rate: sample rate the caller needs [Hz] (e.g. the actuator's acquisition rate); ``None``
            accepts any uniform rate.
        resample: when the file's rate differs from ``expected_rate``, interpolate linearly onto the grid
            ``t0 + i / expected_rate`` covering the file's time span instead of raising. (No anti-alias
            filter is applied: downsampling by a large factor should be filtered beforehand.)
        missing_ok: columns (not ``time``) whose empty or ``nan`` cells are missing samples, read as NaN (a
            reader that can drop samples, such as the online pipeline's current); elsewhere they are errors.
        optional: required columns (``command``, ``position``) the file may lack (a current-only record from an
            on-board system); an absent one reads as NaN throughout.

    Raises:
        ValueError: naming the file and the field: missing file, empty file or header, duplicate or
            missing required columns, a row with the wrong number of cells, a non-numeric cell (line and
            column), a NaN/inf value (column and line), non-increasing or non-uniform time (line), fewer
            than 2 samples, or a sample rate different from ``expected_rate`` (when not resampling).
    """
    path = Path(path)
    if not path.is_file():
        raise ValueError(f"{path}: no such measurement file")
    with open(path, newline="", encoding="utf-8-sig") as fh:  # utf-8-sig: a spreadsheet's byte-order mark
        text = fh.read()
    first = text.split("\n", 1)[0]
    delimiter = "," if "," in first or not any(d in first for d in ";\t") else (";" if ";" in first else "\t")
    rows = list(csv.reader(text.splitlines(), delimiter=delimiter))
    while rows and not any(cell.strip() for cell in rows[-1]):
        rows.pop()  # trailing blank lines
    if not rows:
        raise ValueError(f"{path}: empty file (expected a header row with columns {list(REQUIRED)})")
    header, scales = _read_header(path, rows[0])
    for i, name in enumerate(header):
        if not name:
            raise ValueError(f"{path}: header column {i + 1} is empty")
        if header.index(name) != i:
            raise ValueError(f"{path}: duplicate column {name!r} in the header")
    absent = [c for c in optional if c in REQUIRED and c not in ("time", "current") and c not in header]
    missing = [c for c in REQUIRED if c not in header and c not in absent]
    if missing:
        raise ValueError(f"{path}: missing required column(s) {missing}; header has {header}")
    body = rows[1:]
    if len(body) < 2:
        raise ValueError(f"{path}: need at least 2 data rows, got {len(body)}")

    gaps = {header.index(c) for c in missing_ok if c in header and c != "time"}
    data = np.empty((len(body), len(header)), dtype=np.float64)
    for r, row in enumerate(body):
        line = r + 2
        if len(row) != len(header):
            raise ValueError(f"{path}: line {line} has {len(row)} cells, the header has {len(header)}")
        for c, cell in enumerate(row):
            if c in gaps and cell.strip().lower() in ("", "nan"):
                data[r, c] = math.nan
                continue
            try:
                value = float(cell if delimiter == "," else cell.replace(",", "."))  # decimal commas beside ';'
            except ValueError:
                raise ValueError(f"{path}: line {line}, column {header[c]!r}: non-numeric value {cell!r}") from None
            if not math.isfinite(value):
                raise ValueError(f"{path}: line {line}, column {header[c]!r}: value {cell.strip()!r} is not finite")
            data[r, c] = value

    cols = {name: data[:, i] * scales[i] for i, name in enumerate(header)}
    cols.update({name: np.full(len(body), math.nan) for name in absent})
    time = cols["time"]
    step = np.diff(time)
    bad = np.flatnonzero(step <= 0)
    if bad.size:
        line = int(bad[0]) + 3
        raise ValueError(
            f"{path}: column 'time' is not strictly increasing at line {line} "
            f"({time[bad[0]]!r} -> {time[bad[0] + 1]!r})"
        )
    median = float(np.median(step))
    bad = np.flatnonzero(np.abs(step - median) > TIME_STEP_TOLERANCE * median)
    if bad.size:
        line = int(bad[0]) + 3
        raise ValueError(
            f"{path}: column 'time' is not uniformly sampled at line {line}: step "
            f"{step[bad[0]]:.6g} s, median step {median:.6g} s"
        )
    rate = (len(time) - 1) / float(time[-1] - time[0])

    source_rate = None
    if expected_rate is not None:
        if not (math.isfinite(expected_rate) and expected_rate > 0):
            raise ValueError(f"expected_rate must be a positive number, got {expected_rate!r}")
        if abs(rate - expected_rate) > RATE_TOLERANCE * expected_rate:
            if not resample:
                hint = next(
                    (
                        f" (a time column in {unit}? name it 'time [{unit}]')"
                        for unit, factor in (("ms", 1e3), ("us", 1e6))
                        if abs(rate * factor - expected_rate) <= RATE_TOLERANCE * expected_rate
                    ),
                    "",
                )
                raise ValueError(
                    f"{path}: sample rate {rate:.6g} Hz (from column 'time') differs from the "
                    f"expected {expected_rate:.6g} Hz{hint}; pass resample=True to interpolate"
                )
            source_rate = rate
            n_new = math.floor((time[-1] - time[0]) * expected_rate * (1 + 1e-12)) + 1
            if n_new < 2:
                raise ValueError(
                    f"{path}: resampling {time[-1] - time[0]:.6g} s at {expected_rate:.6g} Hz "
                    "gives fewer than 2 samples"
                )
            new_time = time[0] + np.arange(n_new) / expected_rate
            cols = {name: np.interp(new_time, time, values) for name, values in cols.items() if name != "time"}
            cols["time"] = new_time
            rate = float(expected_rate)

    extra = {name: cols[name] for name in header if name not in REQUIRED}
    return Measurement(
        cols["time"], cols["command"], cols["position"], cols["current"], extra, float(rate), source_rate
    )
