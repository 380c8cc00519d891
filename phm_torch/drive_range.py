"""The drive range: the current a drive with overcurrent protection would have finished a test run within.

One rule for every stage: a record lies within the range when its largest |current| (missing samples ignored) is
at most ``drive_range`` x the actuator's ``current_limit``. Training leaves records beyond it out of the
out-of-distribution calibrations (and, opt-in, out of every fit), phm-evaluate out of every calibration, and the
exported pipeline answers ``overcurrent`` for a record beyond it (:mod:`phm_torch.online.input_contract`).
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import torch


def drive_bound(actuator: Mapping[str, Any] | None, drive_range: float | None) -> float | None:
    """``drive_range`` x the actuator's ``current_limit`` [A] (``actuator``: a provenance record with ``values``);
    None where either is unknown.

    A record beyond it is one a drive with overcurrent protection would not have finished: at k near 1 in two
    phases the shorted pair's inductance is ~(1 - s)^2 of nominal, the current loop becomes unstable at the PWM
    rate and the simulated envelope current swings through kiloamperes (8 % of the 270 V rudder actuator's
    importance-sampled records above twice its 20 A limit, 0.4 % of the reference's above twice its 15 A).
    Such records carry most of the training set's POD energy and inflated the out-of-distribution thresholds
    calibrated on it (the rudder actuator's gappy-residual limit: 28 A with them, 5.0 A without)."""
    if drive_range is None or not actuator:
        return None
    limit = (actuator.get("values") or {}).get("current_limit")
    return None if limit is None else float(drive_range) * float(limit)


def peak_current(current: torch.Tensor) -> torch.Tensor:
    """(B,) the largest |current| of each record (B, n) [A], NaN samples (missing) ignored."""
    return current.nan_to_num(0.0).abs().amax(-1)


def within_drive_range(current: torch.Tensor, bound: float | None) -> torch.Tensor:
    """(B,) True where a record's current (B, n) [A] stays within the drive range ``bound`` [A] (all True without
    one)."""
    if bound is None:
        return torch.ones(current.shape[:-1], dtype=torch.bool, device=current.device)
    return peak_current(current) <= float(bound)
