"""The ``unexplained`` check of the input contract: a near-nominal answer whose record the POD modes explain worse
than its white noise can.

The pipeline's gappy residual r [A] (the RMS of the selected samples the POD modes leave unexplained) of a record
the FDI reads as near nominal (no large fault) is the model's own floor r_0 (the residual of the pipeline's
noise-free nominal record: truncated modes) plus the record's white noise, sigma = noise x RMS current, the noise
the pipeline estimated from second differences. Structure that is neither, coloured noise (pickup, drifting
references) or mains hum, raises r without raising that estimate:

    ratio = r / sqrt(r_0^2 + sigma^2),  flagged above ``UNEXPLAINED_RATIO``.

Only an answer within ``NEAR`` of nominal in every damage component is checked: the floor grows with the damage
(a right answer of backlash 0.2 with gain drift 0.7 had a residual of 4 r_0), and near nominal is where a
confident wrong "healthy" costs most. Measured on the reference actuator's pretrained pipeline (r_0 = 0.031 A;
``scripts/corruption_suite.py``'s 1,000 clean val-like records, 0-3 % white noise): its 118 answers within 0.1 of
nominal (not flagged by the pipeline) reach 1.62 (within 0.2: 2.26; within 0.3: 2.49); 5-40 % white noise added
to the nominal record keeps it at 0.96-1.06. The nominal record read near nominal with 10 / 20 % coloured noise:
2.2 / 3.4, with 10 / 20 / 40 % 400 Hz hum: 2.0 / 3.6 / 6.9. On a 48 V spoiler actuator's small pipeline
(r_0 = 0.0054 A, ``FLOOR_LEVEL``) its 425 clean answers within 0.3 of nominal reach 1.21.
phm-evaluate calibrates a pipeline's own threshold (:func:`calibrate_ratio`, metadata ``unexplained_ratio_max``),
which may only loosen ``UNEXPLAINED_RATIO``.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from types import SimpleNamespace
from typing import Any

import torch

UNEXPLAINED_RATIO = 2.2  # the reference's clean answers within NEAR of nominal reach 1.62: a third above it
NEAR = 0.1  # the largest damage |k_hat - k_0| (phase left out) of an answer the check applies to
# r_0 is taken no lower than this fraction of the nominal RMS current (in quadrature): a pipeline that fits its own
# nominal record almost exactly (a 48 V spoiler actuator's: 1.6e-4 A) saw other noise-free near-nominal records at
# 3.2 times that, where any real noise dominates (at 1 % its ratios stayed below 1.2)
FLOOR_LEVEL = 0.005
CALIBRATION_MARGIN = 1.35  # a pipeline's own threshold: its held-out near answers' largest ratio x this


def residual_floor(run: Callable[[torch.Tensor], Any], nominal: torch.Tensor | None) -> float | None:
    """r_0 [A]: the pipeline's gappy residual of its own noise-free nominal record ``nominal`` (n_full,) [A] (``run``
    the loaded pipeline's ``run``, its result's ``residual``), and ``FLOOR_LEVEL`` x that record's RMS in
    quadrature; None without a nominal record or for a residual that is not finite."""
    if nominal is None or not bool(torch.isfinite(nominal).all()):
        return None
    with torch.no_grad():
        residual = float(run(nominal.reshape(1, -1)).residual[0])
    if not math.isfinite(residual):
        return None
    least = FLOOR_LEVEL * float(nominal.double().pow(2).mean().sqrt())
    return math.sqrt(residual * residual + least * least)


def checked(k_hat: torch.Tensor, nominal: torch.Tensor, mask: torch.Tensor) -> bool:
    """Whether the answer k_hat (8,) is within ``NEAR`` of ``nominal`` (8,) in every damage component (``mask``
    (8,): 1 for a damage, 0 for the phase, as the intervals count them)."""
    return float(((k_hat.double().flatten() - nominal.double()).abs() * mask.double()).max()) < NEAR


def unexplained_ratio(residual: float, noise: float, rms: float, floor: float) -> float:
    """r / sqrt(r_0^2 + (noise x rms)^2): ``residual`` r [A], ``noise`` the relative white-noise level (NaN: none
    counted), ``rms`` the record's RMS current [A], ``floor`` r_0 [A] (:func:`residual_floor`)."""
    sigma = 0.0 if math.isnan(noise) else noise * rms
    return residual / math.sqrt(floor * floor + sigma * sigma)


def calibrate_ratio(pipeline: Any, signals: torch.Tensor, k_hat: torch.Tensor) -> float | None:
    """The check's threshold for an eager pipeline from held-out noisy records (B, n_full) [A] and its estimates
    k_hat (B, 8): ``CALIBRATION_MARGIN`` x the largest ratio of the answers within ``NEAR`` of nominal, and never
    below ``UNEXPLAINED_RATIO`` (a pipeline's own records may only loosen it: an actuator whose modes leave more of
    its near-nominal records unexplained than the reference's). None: nothing to calibrate on."""
    nominal = getattr(pipeline, "nominal_record", None)
    if nominal is None or signals.shape[0] == 0 or nominal.numel() != signals.shape[1]:
        return None
    near = torch.tensor([checked(k, pipeline.nominal, pipeline.interval_mask) for k in k_hat], dtype=torch.bool)
    if not bool(near.any()):
        return None
    x = signals[near].to(pipeline.times.dtype)
    with torch.no_grad():
        floor = residual_floor(lambda r: SimpleNamespace(residual=pipeline(r)[4]), nominal)
        residual, noise = pipeline(x)[4], pipeline.noise_level(x)
    if floor is None:
        return None
    rms = x.double().pow(2).mean(1).sqrt()
    ratios = [unexplained_ratio(float(r), float(n), float(m), floor) for r, n, m in zip(residual, noise, rms)]
    finite = [v for v in ratios if math.isfinite(v)]
    return max(UNEXPLAINED_RATIO, CALIBRATION_MARGIN * max(finite)) if finite else None
