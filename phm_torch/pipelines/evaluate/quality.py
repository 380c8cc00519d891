"""What the exported pipeline is worth on records it was not trained on, carried in the exported file.

phm-evaluate measures the calibrated pipeline's verdict on the held-out split (``fdi_band.split``) and copies the
full online flow's RUL figures of the evaluated split; the result (``held_out_quality``) goes into
rul_calibration.json and the exported file's metadata, so that phm-predict can say, beside each verdict, how often
this pipeline's verdicts of that kind were wrong on this actuator and command
(:mod:`phm_torch.online.quality`). An actuator whose test command does not identify what decides its health
(a robust ball screw: verdict from k_hat 79 % right) then answers with that caveat, not with a bare verdict.

The verdict's figures are read where the pipeline answers (records out of distribution are counted apart); the
classifiers' checkpoint was chosen on this split and the FDI band calibrated on it, so the figures lean towards
optimism, and they are a floor on the error, not an estimate of a bench's.
"""

from __future__ import annotations

import math
from typing import Any

import torch

from ...online import OnlinePipeline

RUL_KEYS = (  # the evaluated split's full-flow RUL figures copied (phm_torch.prognostics.evaluation)
    "rul_vectors",
    "rul_err_median_full_flow",
    "rul_band_coverage_full_flow",
    "rul_uncertainty_median_full_flow",
)


def _finite(value: Any) -> Any:
    """``value``, or None for a NaN (JSON has no NaN)."""
    return None if isinstance(value, float) and math.isnan(value) else value


def held_out_quality(
    pipeline: OnlinePipeline,
    signals: torch.Tensor,
    healthy: torch.Tensor,
    split: str,
    rul_metrics: dict[str, Any],
) -> dict[str, Any]:
    """The pipeline's verdict on held-out records and its full-flow RUL figures.

    Args:
        pipeline: the calibrated online pipeline.
        signals: (N, n_full) noisy current records [A] of the held-out split.
        healthy: (N,) bool, the assessment function's health of each record.
        split: the held-out split's name (recorded).
        rul_metrics: phm-evaluate's metrics of the evaluated split (:data:`RUL_KEYS` are copied when present).

    Returns:
        ``split``, ``records``, ``out_of_distribution`` (fraction), ``faulty_records`` and ``healthy_records`` (in
        distribution), ``missed_faulty`` (fraction of the faulty ones answered healthy), ``false_alarm`` (fraction
        of the healthy ones answered faulty), ``accuracy`` (None where a class is absent), and :data:`RUL_KEYS`.
    """
    if signals.shape[0] != healthy.shape[0]:
        raise ValueError(f"signals hold {signals.shape[0]} records, healthy {healthy.shape[0]}")
    with torch.no_grad():
        _, score, _, ood, _ = pipeline(signals.to(pipeline.times.dtype))
    answered = ~ood.bool()
    said_healthy = (score > 0)[answered]
    truth = healthy.bool()[answered]
    faulty, fine = ~truth, truth

    def share(mask: torch.Tensor, wrong: torch.Tensor) -> float | None:
        return float(wrong[mask].to(torch.float64).mean()) if bool(mask.any()) else None

    n = int(signals.shape[0])
    return {
        "split": split,
        "records": n,
        "out_of_distribution": float((~answered).to(torch.float64).mean()) if n else None,
        "faulty_records": int(faulty.sum()),
        "healthy_records": int(fine.sum()),
        "missed_faulty": share(faulty, said_healthy),
        "false_alarm": share(fine, ~said_healthy),
        "accuracy": float((said_healthy == truth).to(torch.float64).mean()) if bool(answered.any()) else None,
        **{key: _finite(rul_metrics.get(key)) for key in RUL_KEYS},
    }
