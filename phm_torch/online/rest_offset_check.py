"""The ``offset`` check of the input contract: over the rest window (the leading samples where the nominal record has
not left zero yet: the actuator at rest) the record sits off the nominal record by more than ``OFFSET_MAX`` of its
RMS plus four noise standard deviations of the window's mean, unless the answer has two phases shorted at
``REST_SHORTS`` or more.

At rest only a pair of heavily shorted phases draws current (their loop unstable at the PWM rate): over a grid of
two-phase shorts of the reference actuator (``scripts/rest_current_shorts.py``) the rest window's offset reached
the limit from 0.5 and 0.8 (1.1 x; 0.5 and 0.65: 0.08 x), while one short at any level with dry friction or
backlash at 0.8 stayed below 0.05 x, and so did every other of 125 val-like vectors (0.075 x at most). The check
had been skipped for any answer with two large faults, and a bench offset that made the FDI read two (a probe
offset of half the RMS current read as dry friction 0.65 and short_a 0.34) went unflagged.
"""

from __future__ import annotations

import math

import torch

from ..faults import FAULT_NAMES
from ..metrics import finite_mean

REST_LEVEL = 0.02  # the rest window: nominal |current| <= this x its RMS
REST_MIN = 8  # samples: a shorter rest window is no check
OFFSET_MAX = 0.05  # |record - nominal| mean over the rest window, over the nominal RMS (+ 4 noise std)
SHORT_INDEX = tuple(i for i, name in enumerate(FAULT_NAMES) if name.startswith("short_"))
REST_SHORTS = 0.4  # two phases shorted this much in k_hat may draw current at rest (0.5 true, less the FDI's error)


def rest_window(nominal: torch.Tensor) -> int:
    """Samples of the rest window of the nominal record (n,) [A]: its leading samples within ``REST_LEVEL`` x RMS."""
    return int((nominal.abs() <= REST_LEVEL * _rms(nominal)).int().cumprod(0).sum())


def _rms(x: torch.Tensor) -> float:
    return float(x.pow(2).mean().sqrt())


def rest_current_possible(k_hat: torch.Tensor | None) -> bool:
    """Whether the answer k_hat (8,) has two phases shorted at ``REST_SHORTS`` or more (the module note); True
    without an answer (the check is then skipped)."""
    if k_hat is None:
        return True
    shorts = k_hat.flatten()[list(SHORT_INDEX)].double()
    return int((shorts >= REST_SHORTS).sum()) >= 2


def rest_offset(x: torch.Tensor, nominal: torch.Tensor, sigma: float, k_hat: torch.Tensor | None) -> bool:
    """Whether the record x (n,) [A] sits off the nominal record (n,) [A] over the rest window, its white noise
    ``sigma`` [A] allowed for (missing samples left out), for the answer k_hat (8,)."""
    rest = rest_window(nominal)
    if rest < REST_MIN or rest_current_possible(k_hat):
        return False
    mean = float(finite_mean(x[:rest] - nominal[:rest]))
    return abs(mean) > offset_limit(nominal, sigma)


def offset_limit(nominal: torch.Tensor, sigma: float) -> float:
    """The largest rest-window offset [A] the ``offset`` check lets pass: ``OFFSET_MAX`` of the nominal record's (n,)
    RMS plus four noise std (``sigma`` [A] the record's white noise) of the window's mean."""
    return OFFSET_MAX * _rms(nominal) + 4.0 * sigma / math.sqrt(max(rest_window(nominal), 1))


# A near-nominal answer draws no current at rest (a shorted pair does, from 0.5), so over the rest window a clean record
# sits on the nominal one within its noise: over 492 of the inspections of 100 life histories (1 % noise) the window's
# mean stayed within 0.5 % of the nominal RMS, a median 0.11 % (its noise std: 0.14 %). A larger offset there is the
# probe's and is removed (:func:`~.diagnosis.remove_probe_offset`) where the answer without it is near nominal.
# Measured on those histories with a random offset within +-5 % of the RMS current per record: tracked at 21 %
# coverage as read; 83 % removing what exceeds 2.5 noise std; 84 % removing every offset, but the clean ones lost 2.5
# points of coverage and 0.07 of horizon to the noise of the estimate. At 2.5 std the noise alone crossed the gate on
# 1.2 % of clean inspections, and removing that noise moved their near-nominal readings by 0.005-0.011: two sets of
# 100 clean histories lost 0.3-0.7 point of coverage, 1-3 of alpha-lambda and up to 0.018 of horizon. At 3 std (0.27 %
# of clean inspections) the clean histories are within 0.3 point and 0.005 of horizon of no correction, and the
# histories with every corruption keep 79 % coverage (4 std: 75 %).
CORRECT_MIN = 0.0  # the rest-window offset over the nominal RMS ...
CORRECT_SIGMAS = 3.0  # ... plus this many noise std of the window's mean, from which it is removed


def offset_std(nominal: torch.Tensor, sigma: float) -> float:
    """Standard deviation [A] of the rest window's mean of a record with white noise ``sigma`` [A] (the nominal record
    (n,) [A] sets the window): the uncertainty of an offset read there, NaN without a rest window."""
    rest = rest_window(nominal)
    return sigma / math.sqrt(rest) if rest >= REST_MIN else math.nan


def probe_offset(x: torch.Tensor, nominal: torch.Tensor | None, sigma: float) -> float | None:
    """The record x (n,) [A]'s mean offset [A] from the nominal record (n,) [A] over the rest window, where it exceeds
    ``CORRECT_MIN`` of the nominal RMS plus ``CORRECT_SIGMAS`` noise standard deviations of the window's mean
    (``sigma`` [A] the record's white noise); None where it does not, or there is no rest window to read."""
    if nominal is None or x.shape != nominal.shape:
        return None
    rest = rest_window(nominal)
    if rest < REST_MIN:
        return None
    mean = float(finite_mean(x[:rest].double() - nominal[:rest].double()))
    if math.isnan(mean) or abs(mean) <= CORRECT_MIN * _rms(nominal) + CORRECT_SIGMAS * offset_std(nominal, sigma):
        return None
    return mean


# A shorted pair's rest current is the instability of its loop at the PWM rate, never a constant: over the two-short
# records of three actuators' stores whose rest window sat more than 0.5 % of the nominal RMS off, its std was 0.7-2.2
# times its mean. A probe's offset moves the window without spreading it: with 1 % white noise its std read 0.8-1.0
# noise std; noise-free, the reference's val records without a shorted pair spread it by 0.36 % of the nominal RMS at
# most. Coloured noise (5 % of the RMS, corner at f_s / 100) wanders there: (std - 0.5 %) / noise std 1.3-2.8 (5-75 %).
STILL_SIGMAS = 1.3  # a still rest window: std within this many noise std ...
STILL_LEVEL = 0.004  # ... plus this fraction of the nominal RMS


def rest_still(x: torch.Tensor, nominal: torch.Tensor, sigma: float) -> bool:
    """Whether the record x (n,) [A] sits on the nominal record (n,) [A] over the rest window with no more spread than
    its white noise ``sigma`` [A] allows (missing samples left out): a constant shift there, which no shorted pair
    makes. False without a rest window."""
    rest = rest_window(nominal)
    if rest < REST_MIN or x.shape != nominal.shape:
        return False
    d = x[:rest].double() - nominal[:rest].double()
    d = d[torch.isfinite(d)]
    if d.numel() < REST_MIN:
        return False
    return float(d.std()) <= STILL_SIGMAS * sigma + STILL_LEVEL * _rms(nominal)
