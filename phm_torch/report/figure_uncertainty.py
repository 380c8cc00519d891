"""How precisely a run's headline figures are known: bootstrap intervals from its per-record outcomes.

A figure such as err_k or the median RUL error is a statistic of a finite evaluation split (500 val records, 100 rul
vectors at the paper's scale; 100 and 10 at the default one). Comparing two actuators' figures ("within 1.3x of the
reference's") is only meaningful where the ratio's uncertainty is smaller than the distance to the factor. This
module resamples each split's records with replacement (``draws`` times, each split independently) and recomputes
a statistic exactly as the pipeline does (err_k by :func:`~phm_torch.surrogates.metrics.err_k`, the median errors
by :class:`RULComparison`), and draws a proportion (accuracies, missed-fault rates, band coverages, held-out labels,
the workbench's cases) from its counts' Jeffreys posterior.

What the intervals hold: the evaluation split's sampling error alone. A second training on the same store moves the
figures too (two reference runs at the paper's scale: the full-flow RUL error 37 -> 60 %), which no resampling of one
run can see; a ratio called ``within`` or ``outside`` here is decided for that pair of runs only.

Sources (a ``phm-run`` out_dir): ``train/predictions.pt`` (``torch.load(weights_only=True)``: ``k``, ``k_hat``,
``err_alpha``, ``healthy``, ``score``, ``score_chain`` of the val split) and ``evaluate/rul_predictions.json`` (``reference``,
``true_k``, ``full_flow`` RULs (N, 3) [h] of the rul split; -1 stands for a full flow that did not answer).
"""

from __future__ import annotations

import json
import math
from collections.abc import Callable, Mapping
from pathlib import Path

import numpy as np
import torch

from ..prognostics.evaluation import RULComparison
from ..surrogates.metrics import err_k

LEVEL = 0.95  # two-sided interval of every figure and ratio


def _val_statistics(a: Mapping[str, torch.Tensor]) -> dict[str, Callable[[torch.Tensor], float]]:
    """Figure name -> statistic of a set of val rows (index tensor), as train's metrics.json computes it."""
    k, k_hat = a["k"].double(), a["k_hat"].double()
    solved = torch.isfinite(k_hat).all(1)

    def err_k_rows(rows: torch.Tensor) -> float:
        rows = rows[solved[rows]]
        return err_k(k_hat[rows], k[rows]) if rows.numel() else math.nan

    return {"err_k": err_k_rows, "err_alpha_median": lambda rows: float(a["err_alpha"].double()[rows].median())}


def _val_counts(a: Mapping[str, torch.Tensor]) -> dict[str, tuple[int, int]]:
    """Figure name -> (successes, trials) of the val split's proportions: the health classifier's (on the true k)
    and the verdict's (on k_hat) accuracy and missed-fault rate."""
    healthy = a["healthy"].bool()
    out = {}
    for prefix, said in (("classifier", a["score"].double() > 0), ("verdict", a["score_chain"].double() > 0)):
        out[f"{prefix}_accuracy"] = (int((said == healthy).sum()), healthy.numel())
        out[f"{prefix}_missed_fault_rate"] = (int(said[~healthy].sum()), int((~healthy).sum()))
    return out


RUL_ERRORS = ("rul_err_median_true_k", "rul_err_median_full_flow")
RUL_COVERAGES = ("rul_band_coverage_true_k", "rul_band_coverage_full_flow")


def _draw(n: int, draws: int, rng: np.random.Generator) -> torch.Tensor:
    """(draws, n) row indices resampled with replacement."""
    if n < 1:
        raise ValueError(f"a split to resample needs at least one record, got {n}")
    return torch.from_numpy(rng.integers(0, n, size=(draws, n)))


def proportion_draws(successes: int, n: int, draws: int = 1000, seed: int = 0) -> np.ndarray:
    """Draws (draws,) of a proportion observed as successes of n: its Jeffreys posterior Beta(s + 1/2, n - s + 1/2).
    Unlike resampling the n outcomes, it does not collapse to a point at 0 of n or n of n (26 of 26 bands holding
    the truth: 95 % interval [0.91, 1.00], not [1, 1]); elsewhere it is as wide as the binomial's."""
    if n < 1 or not 0 <= successes <= n:
        raise ValueError(f"a proportion needs 0 <= successes <= n and n >= 1, got {successes} of {n}")
    return np.random.default_rng(seed).beta(successes + 0.5, n - successes + 0.5, size=draws)


def run_figure_draws(run: Path, draws: int = 1000, seed: int = 0) -> dict[str, np.ndarray]:
    """Draws (draws,) of every figure a ``phm-run`` out_dir's per-record files give: the val split's err_k and
    err_alpha median (resampled records), the health classifier's (on the true k) and the verdict's (on k_hat)
    accuracy and missed-fault rate (:func:`proportion_draws`); the rul split's median RUL errors (resampled) and
    band coverages (proportions). A figure whose source file is missing is left out."""
    if draws < 100:
        raise ValueError(f"draws must be >= 100 for a {LEVEL:.0%} interval, got {draws}")
    rng = np.random.default_rng(seed)
    out: dict[str, np.ndarray] = {}
    val = run / "train" / "predictions.pt"
    if val.is_file():
        arrays = torch.load(val, map_location="cpu", weights_only=True)
        idx = _draw(arrays["k"].shape[0], draws, rng)
        for name, stat in _val_statistics(arrays).items():
            out[name] = np.array([stat(rows) for rows in idx])
        for i, (name, (hits, n)) in enumerate(_val_counts(arrays).items()):
            out[name] = proportion_draws(hits, n, draws, seed + 1 + i) if n else np.full(draws, math.nan)
    rul = run / "evaluate" / "rul_predictions.json"
    if rul.is_file():
        p = json.loads(rul.read_text())
        ref, true_k = (torch.tensor(p[key], dtype=torch.float64) for key in ("reference", "true_k"))
        flow = torch.tensor(p["full_flow"], dtype=torch.float64)
        flow[flow < 0] = math.nan  # the file writes a full flow that did not answer as -1
        idx = _draw(ref.shape[0], draws, rng)
        table = [RULComparison(ref[rows], true_k[rows], flow[rows]).metrics() for rows in idx]
        for name in RUL_ERRORS:
            out[name] = np.array([m[name] for m in table])
        # a coverage is a proportion of the vectors with a positive reference RUL: its count from the evaluation's own
        full = RULComparison(ref, true_k, flow).metrics()
        n = full["rul_vectors"] - full["rul_reference_faulty"]
        for i, name in enumerate(RUL_COVERAGES):
            inside = round(full[name] * n) if n else 0
            out[name] = proportion_draws(inside, n, draws, seed + 11 + i) if n else np.full(draws, math.nan)
    return out


def interval(values: np.ndarray) -> tuple[float, float]:
    """The central ``LEVEL`` interval of finite draws (NaN, NaN without any)."""
    finite = values[np.isfinite(values)]
    if not finite.size:
        return math.nan, math.nan
    tail = (1 - LEVEL) / 2
    return float(np.quantile(finite, tail)), float(np.quantile(finite, 1 - tail))


def ratio_status(base: np.ndarray, other: np.ndarray, smaller_is_better: bool, factor: float) -> dict[str, float | str]:
    """The ratio other / base of two independent draws' figures: its interval and whether the target (``factor``;
    at most ``factor`` for an error, at least 1 / ``factor`` for an accuracy) is met on all of it (``within``), on
    none of it (``outside``) or on part (``undecided``)."""
    if factor < 1:
        raise ValueError(f"factor must be >= 1, got {factor}")
    n = min(base.size, other.size)
    with np.errstate(divide="ignore", invalid="ignore"):
        ratio = other[:n] / base[:n]
    lo, hi = interval(ratio)
    if math.isnan(lo):
        return {"ratio_lo": lo, "ratio_hi": hi, "status": "undecided"}
    if smaller_is_better:
        status = "within" if hi <= factor else "outside" if lo > factor else "undecided"
    else:
        status = "within" if lo >= 1 / factor else "outside" if hi < 1 / factor else "undecided"
    return {"ratio_lo": lo, "ratio_hi": hi, "status": status}


__all__ = ["LEVEL", "RUL_COVERAGES", "RUL_ERRORS", "interval", "proportion_draws", "ratio_status", "run_figure_draws"]
