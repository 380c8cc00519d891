"""The input contract's ``spikes`` check: single-sample spikes far above a record's noise and its own steps.

A spike is a second difference ``|x[i+1] - 2 x[i] + x[i-1]|`` above both ``SPIKE_SIGMA`` noise std of a second
difference of white noise (sqrt(6) sigma) and ``step`` x the RMS current (the nominal record's, or the record's own
where larger: a record drawing more current steps more), the most the filtered current steps by itself.
``SPIKE_STEP`` (0.8) was measured on the reference at 20 kHz, where clean records with no large fault step by at
most 0.39 of that RMS. The second difference of a smooth current grows as the square of
the sampling period: at 5 kHz the same records step by 0.5-0.9, so a pipeline calibrates its own ``step`` on
held-out records (:func:`calibrate_spike_step`, metadata ``spike_step_max``), never below ``SPIKE_STEP``.
"""

from __future__ import annotations

import math
from typing import Any

import torch

from .fault_count import no_large_fault

SPIKE_SIGMA = 12.0  # a spike: a second difference above this many noise std of a second difference...
SPIKE_STEP = 0.8  # ... and above this fraction of the nominal RMS current (the current's own steps)
SPIKE_MARGIN = 1.5  # a calibrated step: this x the largest step of the held-out records with no large fault


def largest_step(x: torch.Tensor) -> torch.Tensor:
    """The largest |second difference| (B,) of records x (B, n) or () of one record (n,) [A], over finite ones."""
    d2 = (x[..., 2:] - 2.0 * x[..., 1:-1] + x[..., :-2]).abs()
    return torch.where(torch.isfinite(d2), d2, torch.zeros_like(d2)).amax(-1)


def has_spikes(x: torch.Tensor, sigma: float, scale: float, step: float = SPIKE_STEP) -> bool:
    """Whether the record x (n,) [A] with white-noise std ``sigma`` [A] has a spike, ``scale`` [A] the larger of the
    nominal record's RMS current and the record's own, ``step`` the pipeline's threshold (fraction of ``scale``)."""
    if x.numel() < 3:
        return False
    return float(largest_step(x)) > max(SPIKE_SIGMA * math.sqrt(6.0) * sigma, step * scale)


def calibrate_spike_step(model: Any, signals: torch.Tensor, k_hat: torch.Tensor) -> float | None:
    """The ``spikes`` check's step for a pipeline: ``SPIKE_MARGIN`` x the largest second difference, over the
    larger of the nominal record's RMS and the record's own, of the held-out records (B, n_full) [A] whose estimate
    (k_hat (B, 8)) has no large fault, never below ``SPIKE_STEP``. None: nothing to calibrate on."""
    nominal = getattr(model, "nominal_record", None)
    if nominal is None or nominal.numel() != signals.shape[1]:
        return None
    none_large = no_large_fault(model, k_hat)
    if not bool(none_large.any()):
        return None
    scale = float(nominal.double().pow(2).mean().sqrt())
    if not scale > 0:
        return None
    x = signals[none_large].double()
    own = torch.where(torch.isfinite(x), x, torch.zeros_like(x)).pow(2).mean(1).sqrt()
    steps = largest_step(x) / own.clamp(min=scale)
    return max(SPIKE_STEP, SPIKE_MARGIN * float(steps.max()))
