"""The verdict classifier: a health classifier fitted on the FDI's *estimates* of the training signals.

The health classifier f(k) replaces the assessment function on the true fault vector: 99 % right on the
paper store, and the RUL integration's stopping event. A measured actuator only offers k_hat, and
sign f(k_hat) is right 92-93 % of the time on 4,000 unseen paper-scale signals (docs/surrogates.md): near
the boundary the FDI error moves vectors across it, and its bias there (estimates shrink towards the
common, mildly damaged vectors) turns faults into "healthy" verdicts (6-8 % missed faults). The Bayes
decision from k_hat is a different boundary: the one that separates the *estimates* of healthy and faulty
actuators. :func:`fit_verdict_classifier` learns it from the training signals themselves (their
estimates with the rated measurement noise, their true labels): 95 % right and 3 % missed faults on the same
4,000 signals. f(k) stays the RUL event: the propagated trajectory is a fault vector, not an estimate.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import torch

from .augment import add_noise
from .classifiers.base import HealthClassifier
from .metrics import confusion

Estimator = Callable[[torch.Tensor, torch.Tensor], torch.Tensor]
BLOCK_ROWS = 8192  # records per FDI call: the network's hidden activations of a block stay small


@torch.no_grad()
def noisy_estimates(
    estimate: Estimator,
    samples: torch.Tensor,
    scale: torch.Tensor,
    noise: float,
    seed: int,
    block_rows: int = BLOCK_ROWS,
) -> torch.Tensor:
    """FDI estimates k_hat (N, 8) float64 of records whose selected samples get white noise.

    Args:
        estimate: (samples (B, n_w) [A], relative noise level (B,)) -> k_hat (B, 8), e.g.
            ``lambda s, lvl: network(gappy(s)[0], lvl)``.
        samples: (N, n_w) noise-free samples of the training records [A].
        scale: (N,) the records' RMS current [A]; the noise std is ``noise`` x scale.
        noise: relative noise std (the rated measurement noise, ``eval.noise``); 0: none.
        seed: seeds the noise draw (block by block, so the result does not depend on memory).
    """
    if not noise >= 0.0:
        raise ValueError(f"verdict classifier: noise must be >= 0, got {noise!r}")
    if samples.ndim != 2 or scale.shape != samples.shape[:1]:
        raise ValueError(
            f"verdict classifier: samples must be (N, n_w) and scale (N,), got "
            f"{tuple(samples.shape)} and {tuple(scale.shape)}"
        )
    gen = torch.Generator().manual_seed(seed)
    out = []
    for rows, sc in zip(samples.split(block_rows), scale.split(block_rows), strict=True):
        level = torch.full((rows.shape[0],), float(noise), dtype=rows.dtype)
        noisy = add_noise(rows, sc, noise, gen) if noise > 0 else rows
        out.append(estimate(noisy, level).to(torch.float64))
    return torch.cat(out) if out else torch.zeros(0, 8, dtype=torch.float64)


def fit_verdict_classifier(
    classifier: HealthClassifier,
    estimate: Estimator,
    samples: torch.Tensor,
    scale: torch.Tensor,
    healthy: torch.Tensor,
    noise: float,
    seed: int,
    max_missed_fault_rate: float | None = None,
) -> HealthClassifier:
    """Fit ``classifier`` (unfitted) on the estimates of the training records and their true labels.

    Args as :func:`noisy_estimates`; ``healthy`` (N,) bool, the records' assessed health;
    ``max_missed_fault_rate``: None, or raise the threshold until at most this fraction of the faulty
    records' estimates score healthy (:meth:`HealthClassifier.calibrate`, the same trade as for the health
    classifier: fewer missed faults for more false alarms). Returns the fitted classifier, whose
    ``predict(k_hat)`` is the verdict on a measured actuator.
    """
    if healthy.shape != samples.shape[:1]:
        raise ValueError(f"verdict classifier: healthy must be ({samples.shape[0]},), got {tuple(healthy.shape)}")
    k_hat = noisy_estimates(estimate, samples, scale, noise, seed)
    classifier.fit(k_hat, healthy.bool())
    if max_missed_fault_rate is not None:
        classifier.calibrate(k_hat, healthy.bool(), max_missed_fault_rate)
    return classifier


def calibrate_verdict_held_out(
    verdict: HealthClassifier, k_hat: torch.Tensor, healthy: torch.Tensor, rate: float
) -> dict[str, Any]:
    """Raise the verdict's threshold until at most ``rate`` of the faulty held-out records' estimates k_hat (N, 8)
    score healthy (``healthy`` (N,) their assessed health); returns what the calibration saw and set."""
    healthy = healthy.bool()
    before = confusion(verdict.predict(k_hat), healthy)
    verdict.calibrate(k_hat, healthy, rate)
    after = confusion(verdict.predict(k_hat), healthy)
    return {
        "max_missed_fault_rate": rate,
        "n_held_out": int(healthy.numel()),
        "n_faulty": int((~healthy).sum()),
        "threshold": float(verdict.threshold),
        "held_out_missed_fault_rate": [before["missed_fault_rate"], after["missed_fault_rate"]],
        "held_out_false_alarm_rate": [before["false_alarm_rate"], after["false_alarm_rate"]],
    }
