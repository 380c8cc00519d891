"""How many large faults an estimate holds, as a pipeline's k intervals count them: the near-nominal checks
of the input contract apply to the records with none, and the calibrations of their thresholds (``shape``,
``spikes``) read the held-out records with none."""

from __future__ import annotations

from typing import Any

import torch


def large_faults(model: Any, k_hat: torch.Tensor | None) -> int | None:
    """Large faults in k_hat (8,), as the pipeline's intervals count them; None without an estimate or a count."""
    try:
        level, nominal, mask = float(model.interval_level), model.nominal, model.interval_mask
    except (AttributeError, RuntimeError):
        return None
    if k_hat is None:
        return None
    return int((((k_hat.to(nominal.dtype).flatten() - nominal).abs() * mask) > level).sum())


def no_large_fault(model: Any, k_hat: torch.Tensor) -> torch.Tensor:
    """(B,) bool: the estimates k_hat (B, 8) with no large fault, as the pipeline's intervals count them (the
    records the near-nominal checks apply to)."""
    return torch.tensor([large_faults(model, k) == 0 for k in k_hat], dtype=torch.bool)
