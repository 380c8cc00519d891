"""A stand-in for an exported pipeline as the input contract's near-nominal checks read it: its nominal record,
nominal fault vector and interval level (large faults: ``|k_hat - k_0| > 0.3``, the phase k7 left out)."""

from __future__ import annotations

from types import SimpleNamespace

import torch


def contract_model(nominal_record: torch.Tensor) -> SimpleNamespace:
    """The attributes of an exported pipeline the contract's shape, spike and unexplained checks read."""
    return SimpleNamespace(
        nominal_record=nominal_record,
        interval_level=0.3,
        nominal=torch.tensor([0.0] * 6 + [0.5, 0.5], dtype=torch.float64),
        interval_mask=torch.tensor([1.0] * 6 + [0.0, 1.0], dtype=torch.float64),
        n_full=int(nominal_record.numel()),
    )
