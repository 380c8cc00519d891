"""A current probe's gain and offset, read off the bench's healthy record: ``baseline`` calibrates the probe.

``phm-predict baseline=`` (and phm-track's) moves every record onto the training model by subtracting the bench's
difference at nominal (:meth:`~phm_torch.online.OnlinePipeline.rebase`): exact for an additive difference, not for
a probe's gain, which scales every fault's signature too. A probe at x1.05 with a zero 5 % of the RMS current off
read the bench's own healthy record 13 interval half-widths from nominal: every record refused (``bench``), and
without a baseline every first inspection of a fleet read four damages at +0.06 to +0.1 (``fleet_offset``).

A probe error is affine, ``measured = gain * current + offset``, and the bench's healthy record shows it: fitted by
least squares on the training model's nominal record, a probe error leaves only the record's noise, while a
physical difference between the bench and the training model leaves a structured residual. Over the library's
effects at half strength (HF records of the reference actuator, ``scripts/trust_model_mismatch.py``'s benches) an
affine fit explained at most 79 % of the healthy record's difference (a viscous or temperature difference is partly a
gain, never wholly), a x1.05 probe with a 5 % offset 98.8 % at 1 % noise. Above ``EXPLAINED_MIN`` the bench's
records are read through the inverse map, ``(measured - offset) / gain``, before the rebase and the bench check;
below it (or for a difference too small to matter) nothing is changed.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import torch

EXPLAINED_MIN = 0.95  # share of the healthy record's difference from nominal an affine map must explain
GAIN_MIN = 0.005  # |gain - 1| ...
OFFSET_MIN = 0.005  # ... or |offset| / nominal RMS above which the calibration is applied (else: nothing to do)
GAIN_RANGE = (0.5, 2.0)  # a probe gain outside it is no calibration error (the checks refuse such a bench)


@dataclass(frozen=True)
class ProbeCalibration:
    """The bench's probe: ``measured = gain * current + offset`` [A]; ``explained`` the share of its healthy
    record's difference from the nominal record the map explains."""

    gain: float
    offset: float
    explained: float

    def apply(self, current: torch.Tensor) -> torch.Tensor:
        """The current (..., n) [A] the probe measured, as the training model's probe reads it."""
        return (current - self.offset) / self.gain

    def message(self) -> str:
        return (
            f"the bench's healthy baseline record reads as the nominal one through a probe of gain {self.gain:.4f} "
            f"and offset {self.offset:+.4g} A ({100 * self.explained:.1f} % of its difference explained): every "
            "record is read through the inverse map before the baseline"
        )

    def as_dict(self) -> dict[str, Any]:
        return {"gain": self.gain, "offset": self.offset, "explained": self.explained}


def fit_probe(baseline: torch.Tensor, nominal: torch.Tensor | None) -> ProbeCalibration | None:
    """The probe error the bench's healthy record ``baseline`` (n_full,) [A] shows against the training model's
    nominal record (n_full,) [A] (missing samples left out), or None: no nominal record to compare with, a difference
    an affine map does not explain (``EXPLAINED_MIN``), one too small to matter, or a gain outside ``GAIN_RANGE``."""
    if nominal is None or baseline.shape != nominal.shape or not bool(torch.isfinite(nominal).all()):
        return None
    b, n = baseline.double(), nominal.double()
    present = torch.isfinite(b)
    b, n = b[present], n[present]
    if b.numel() < 3:
        return None
    design = torch.stack([n, torch.ones_like(n)], 1)
    gain, offset = torch.linalg.lstsq(design, b.unsqueeze(1)).solution[:, 0].tolist()
    difference = float((b - n).pow(2).sum())
    residual = float((b - design @ torch.tensor([gain, offset], dtype=b.dtype)).pow(2).sum())
    explained = 1.0 - residual / difference if difference > 0 else 0.0
    rms = math.sqrt(float(n.pow(2).mean()))
    small = abs(gain - 1.0) <= GAIN_MIN and abs(offset) <= OFFSET_MIN * rms
    if small or explained < EXPLAINED_MIN or not GAIN_RANGE[0] <= gain <= GAIN_RANGE[1]:
        return None
    return ProbeCalibration(gain, offset, explained)
