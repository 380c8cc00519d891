"""Bench lines in the workbench's records: a line through the whole measured current that the calibrated model does not
make is the bench's (mains hum on the probe), not an effect of the actuator.

Left in, a hum keeps the residual above the noise floor whatever effect is added, and the workbench then fits a neural
closure to it (a 400 Hz hum of 10 % of the RMS current on the hidden-cogging example: cogging found, then a closure
on the hum). :func:`bench_lines` finds the lines of each record's measured current
(:func:`~phm_torch.online.bench_lines.find_lines`) and keeps those the model's simulated current of that record has
no line within ``MATCH_HZ`` of (at half the share or more), and none that a rotor-angle harmonic at a steady motor
speed could be (a slewed command turns the motor at a steady speed, where cogging is a line in time too; the model
without that effect would not make it).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import asdict, replace
from typing import Any

import torch

from ..online.bench_lines import Line, find_lines, remove_lines
from .data import Record

MATCH_HZ = 1.0  # a measured line and a simulated one within this are the same line
STEADY = 0.2  # a motor speed whose std is below this fraction of its mean is steady ...
ORDER_TOLERANCE = 0.02  # ... and a line within this fraction of an integer order of it may be the rotor's


def _steady_orders(record: Record, gear_ratio: float, max_order: int) -> list[float]:
    """The frequencies [Hz] of the rotor-angle orders 1..``max_order`` at the record's motor speed, where that speed
    is steady ([] where it is not: a chirp about zero)."""
    position = record.measured.get("position", record.extra.get("position"))
    source = record.command if position is None else position
    speed = torch.diff(source.double()) * record.sample_rate * gear_ratio  # [rad/s at the motor]
    mean = float(speed.mean())
    if not (abs(mean) > 0 and float(speed.std()) < STEADY * abs(mean)):
        return []
    turn = abs(mean) / (2.0 * math.pi)  # motor turns a second
    return [order * turn for order in range(1, max_order + 1)]


def _may_be_rotor(line: Line, orders: Sequence[float]) -> bool:
    return any(abs(line.frequency - f) <= ORDER_TOLERANCE * f for f in orders)


def bench_lines(
    records: Sequence[Record], simulated: Sequence[dict[str, torch.Tensor]], gear_ratio: float, max_order: int
) -> dict[str, list[Line]]:
    """{record name: its bench lines} for the records whose measured current has lines the calibrated model's
    ``simulated`` current (one {channel: (n,)} per record) does not make (module note)."""
    out: dict[str, list[Line]] = {}
    for record, sim in zip(records, simulated):
        if "current" not in record.measured:
            continue
        measured = find_lines(record.measured["current"], record.sample_rate)
        if not measured:
            continue
        model = find_lines(sim["current"].detach().cpu(), record.sample_rate) if "current" in sim else []
        orders = _steady_orders(record, gear_ratio, max_order)
        own = [
            line
            for line in measured
            if not any(abs(line.frequency - m.frequency) <= MATCH_HZ and m.share >= 0.5 * line.share for m in model)
            and not _may_be_rotor(line, orders)
        ]
        if own:
            out[record.name] = own
    return out


def without_lines(records: Sequence[Record], lines: dict[str, list[Line]]) -> list[Record]:
    """The records with their bench ``lines`` removed from the measured current."""
    out = []
    for record in records:
        found = lines.get(record.name)
        if found:
            current = remove_lines(record.measured["current"], record.time, found)
            record = replace(record, measured={**record.measured, "current": current})
        out.append(record)
    return out


def as_json(lines: dict[str, list[Line]]) -> dict[str, list[dict[str, Any]]]:
    return {name: [asdict(line) for line in found] for name, found in lines.items()}
