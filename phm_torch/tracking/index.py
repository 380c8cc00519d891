"""The inspection index of a fleet: a CSV with columns ``actuator,hours,file`` (and optionally ``event``).

One row per inspection; ``file`` is a measurement CSV (phm-predict's format) relative to the index; hours
[h] are the actuator's operating hours since new (the tracker's prior of a component the FDI does not identify is
the damage law's prediction from new over them) and increase strictly within an actuator (rows of different
actuators may interleave); ``event`` is empty or ``maintenance`` (the actuator was overhauled before this
inspection: its track starts again). Every problem is one ValueError naming the index, its line (the header is
line 1) and the value.
"""

from __future__ import annotations

import csv
import math
import os
from dataclasses import dataclass
from pathlib import Path

REQUIRED = ("actuator", "hours", "file")
EVENTS = ("", "maintenance")


@dataclass(frozen=True)
class Inspection:
    """One row of the index: ``line`` its line in the CSV, ``path`` the record's file resolved against the
    index's folder, ``file`` as written in the index."""

    actuator: str
    hours: float
    file: str
    path: Path
    event: str
    line: int


def read_index(path: str | os.PathLike, check_files: bool = True) -> dict[str, list[Inspection]]:
    """{actuator: its inspections in time order}, actuators in order of first appearance."""
    path = Path(path)
    if not path.is_file():
        raise ValueError(f"index: no such file {str(path)!r}")
    with open(path, newline="") as fh:
        rows = list(csv.reader(fh))
    if not rows:
        raise ValueError(f"{path}: empty index (expected a header with columns {list(REQUIRED)})")
    header = [h.strip() for h in rows[0]]
    missing = [c for c in REQUIRED if c not in header]
    if missing:
        raise ValueError(
            f"{path}: missing column(s) {missing} (header {header}; expected {list(REQUIRED)} and optionally 'event')"
        )
    col = {name: header.index(name) for name in header}
    out: dict[str, list[Inspection]] = {}
    seen: dict[tuple[str, float], int] = {}
    for line, row in enumerate(rows[1:], start=2):
        if not any(cell.strip() for cell in row):
            continue
        if len(row) != len(header):
            raise ValueError(f"{path} line {line}: {len(row)} cells, the header has {len(header)}")
        actuator = row[col["actuator"]].strip()
        if not actuator:
            raise ValueError(f"{path} line {line}: empty actuator")
        text = row[col["hours"]].strip()
        try:
            hours = float(text)
        except ValueError:
            raise ValueError(f"{path} line {line} (actuator {actuator}): hours {text!r} is not a number") from None
        if not math.isfinite(hours) or hours < 0:
            raise ValueError(f"{path} line {line} (actuator {actuator}): hours {text!r} must be finite and >= 0")
        event = row[col["event"]].strip() if "event" in col else ""
        if event not in EVENTS:
            raise ValueError(
                f"{path} line {line} (actuator {actuator}): unknown event {event!r} (known: 'maintenance', or empty)"
            )
        if (actuator, hours) in seen:
            raise ValueError(
                f"{path} line {line} (actuator {actuator}): duplicate hours {hours:g} (line {seen[(actuator, hours)]})"
            )
        seen[(actuator, hours)] = line
        previous = out.get(actuator, [])
        if previous and hours <= previous[-1].hours:
            raise ValueError(
                f"{path} line {line} (actuator {actuator}): hours {hours:g} not after the previous "
                f"inspection's {previous[-1].hours:g} (line {previous[-1].line})"
            )
        name = row[col["file"]].strip()
        record = (path.parent / name) if name else path.parent
        if check_files and not (name and record.is_file()):
            raise ValueError(
                f"{path} line {line} (actuator {actuator}): no such file {name!r} "
                f"(paths are relative to the index's folder {str(path.parent)!r})"
            )
        out.setdefault(actuator, []).append(Inspection(actuator, hours, name, record, event, line))
    if not out:
        raise ValueError(f"{path}: no inspections")
    return out
