"""Per-parameter intervals for an FDI estimate: split-conformal half-widths by difficulty class.

k_hat is a point estimate whose error depends strongly on how many damage parameters are large at once
(docs/surrogates.md, "where err_k fails": err_k 1.5 % with none, 15 % with three or more). One error bar
for every record would be far too wide near nominal and too narrow in multiple faults. So the records
are put in ``n_classes`` difficulty classes by the number of large faults *of the estimate*
(|k_hat_i - k0_i| > ``level``, k7 not counted, the last class holding that many or more), which the
online step can compute, and each class gets its own half-width per parameter: the split-conformal
quantile of |k_hat_i - k_i| on held-out records (``ceil((n + 1) c) / n``-th quantile for coverage c),
so that a new record of the same population falls in [k_hat - w, k_hat + w] (clipped to [0, 1]) with
probability at least c per parameter.

A class with fewer than ``min_count`` held-out records is pooled with the classes below it (the hardest
class, usually the smallest, has no other neighbours), and the widths are made non-decreasing with the
class, so that a harder class never gets a narrower interval than an easier one. The eccentricity phase k7 is only
observable when the eccentricity k6 is large; its interval is close to [0, 1] otherwise, as it should be.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from ..surrogates.metrics import fault_count

DEFAULT_LEVEL = 0.3  # "large fault", as in metrics.fault_count and err_k_by_fault_count
DEFAULT_CLASSES = 4  # 0, 1, 2, 3 or more large faults


@dataclass
class FDIInterval:
    """Calibrated half-widths.

    Attributes:
        half_widths: (n_classes, 8) half-width per difficulty class and parameter [k units].
        counts: held-out records per class (before pooling).
        pooled_from: per class, the lowest class whose records its half-widths were computed from.
        level: damage above which a parameter counts as a large fault [k units].
        coverage: the per-parameter coverage the half-widths were calibrated for.
    """

    half_widths: torch.Tensor
    counts: list[int]
    pooled_from: list[int]
    level: float
    coverage: float


def difficulty_class(k_hat: torch.Tensor, nominal: torch.Tensor, level: float, n_classes: int) -> torch.Tensor:
    """(B,) int64 difficulty class of estimates k_hat (B, 8): their number of large faults, capped at
    ``n_classes - 1``."""
    return fault_count(k_hat, nominal, level).clamp(max=n_classes - 1)


def calibrate_fdi_interval(
    k_hat: torch.Tensor,
    k: torch.Tensor,
    nominal: torch.Tensor,
    coverage: float,
    min_count: int,
    level: float = DEFAULT_LEVEL,
    n_classes: int = DEFAULT_CLASSES,
) -> FDIInterval:
    """Split-conformal half-widths of k_hat per difficulty class, from held-out records.

    Args:
        k_hat: (N, 8) FDI estimates of held-out records (in distribution; e.g. with measurement noise).
        k: (N, 8) their true fault vectors.
        nominal: (8,) nominal fault vector k0.
        coverage: per-parameter coverage c in (0, 1) of the intervals.
        min_count: fewest records a class's widths are computed from (>= 1; smaller classes are pooled
            with the classes below them). There must be at least this many records in all.
        level: damage above which a parameter counts as a large fault (> 0).
        n_classes: difficulty classes (>= 1); 1 = one half-width per parameter for every record.
    """
    if not 0.0 < coverage < 1.0:
        raise ValueError(f"fdi_interval.coverage must be in (0, 1), got {coverage!r}")
    if not level > 0:
        raise ValueError(f"fdi_interval.level must be > 0, got {level!r}")
    if isinstance(n_classes, bool) or not isinstance(n_classes, int) or n_classes < 1:
        raise ValueError(f"fdi_interval.n_classes must be an integer >= 1, got {n_classes!r}")
    if isinstance(min_count, bool) or not isinstance(min_count, int) or min_count < 1:
        raise ValueError(f"fdi_interval.min_count must be an integer >= 1, got {min_count!r}")
    if k_hat.shape != k.shape or k.ndim != 2 or k.shape[1] != 8:
        raise ValueError(f"k_hat {tuple(k_hat.shape)} and k {tuple(k.shape)} must both be (N, 8)")
    if k.shape[0] < min_count:
        raise ValueError(f"fdi_interval: {k.shape[0]} calibration records, at least min_count={min_count} needed")
    k_hat, k = k_hat.to(torch.float64), k.to(torch.float64)
    nominal = torch.as_tensor(nominal, dtype=torch.float64)
    cls = difficulty_class(k_hat, nominal, level, n_classes)
    error = (k_hat - k).abs()
    counts = [int((cls == c).sum()) for c in range(n_classes)]
    widths, pooled_from = torch.zeros(n_classes, 8, dtype=torch.float64), []
    for c in range(n_classes):
        low, high = c, c
        while sum(counts[low : high + 1]) < min_count:  # pool with the classes below, then (the easiest
            if low > 0:  # class, when sparse) with those above
                low -= 1
            else:
                high += 1
        rows = error[(cls >= low) & (cls <= high)]
        n = rows.shape[0]
        widths[c] = torch.quantile(rows, min(1.0, math.ceil((n + 1) * coverage) / n), dim=0)
        if c > 0:
            widths[c] = torch.maximum(widths[c], widths[c - 1])
        pooled_from.append(low)
    return FDIInterval(widths, counts, pooled_from, float(level), float(coverage))


def interval_quality(lower: torch.Tensor, upper: torch.Tensor, k: torch.Tensor) -> dict[str, list[float]]:
    """Per-parameter coverage (fraction of the true k inside [lower, upper]) and mean width of intervals
    (B, 8) each, against the true fault vectors k (B, 8)."""
    inside = (k >= lower) & (k <= upper)
    return {
        "coverage": inside.to(torch.float64).mean(0).tolist(),
        "width": (upper - lower).to(torch.float64).mean(0).tolist(),
    }
