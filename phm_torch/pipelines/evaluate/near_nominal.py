"""The records phm-evaluate calibrates the near-nominal checks on (``shape``, ``unexplained``, ``spikes``: each
applies to an answer without a large fault, and each threshold is the loosest of its clean near-nominal records,
widened, never stricter than the reference's measured default).

Held-out records near nominal in truth, first. A robust actuator's store has few: reaching its healthy-fraction
target puts the sampled vectors far from nominal (the 28 V ball-screw sketch's default-scale val split held 3 of 100,
one of them answered near nominal), and a threshold read off one record is that record's. That ball screw's shape
threshold came out at 0.776 from its one record, and then refused 170 of the 843 clean inspections of its own life
histories (9 % of those with every damage below 0.05, 39-50 % of those between 0.05 and 0.2). So below
``NEAR_MIN_ROWS`` held-out records the training split's records near nominal in truth are added, with the same
measurement noise. None of the three statistics is the FDI's fit: a record's correlation with the nominal record and
its largest step are the record's own, and the gappy residual of a training record can only be smaller than a new
one's, so a training row never makes a threshold stricter than the held-out rows alone would.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from types import SimpleNamespace
from typing import Any

import torch

from ...drive_range import within_drive_range
from ...online.fault_count import no_large_fault
from .calibration import noisy

log = logging.getLogger(__name__)

NEAR_MIN_ROWS = 30  # held-out rows below which the training split's are added (~ the 3 % tail's lowest of 30)
TRAINING_ROWS_MAX = 2000  # training rows read at most (a paper-scale store holds thousands near nominal)


def near_nominal_rows(pipeline: Any, k_true: torch.Tensor, ood: torch.Tensor) -> torch.Tensor:
    """(B,) bool: the records the near-nominal checks (shape, unexplained, spikes) calibrate on: in distribution and
    with no large fault in their true k (B, 8). Each check then keeps those its FDI also answers near nominal. Not
    every record the FDI answers near nominal: an FDI that identifies the command poorly (a 28 V ball screw: R^2
    0.03-0.67) reads faulty records as near nominal, and calibrating on them widened the shape threshold to -0.58, a
    check that refuses nothing, where it exists to refuse exactly those answers."""
    return ~ood.to(torch.bool) & no_large_fault(pipeline, k_true)


def near_nominal_calibration(
    pipeline: Any,
    held_out: SimpleNamespace,
    training_k: torch.Tensor | None,
    read_training: Callable[[list[int]], torch.Tensor] | None,
    noise: float,
    seed: int,
    drive_bound: float | None = None,
) -> SimpleNamespace:
    """The near-nominal checks' calibration records: the held-out ones near nominal in truth, and where they are
    fewer than ``NEAR_MIN_ROWS``, the training split's too.

    Args:
        pipeline: the calibrated pipeline (its intervals count the large faults); called on (B, n_full) records.
        held_out: ``signals`` (B, n_full) [A] noisy held-out records, ``k`` (B, 8) their truth, ``k_hat`` (B, 8) and
            ``ood`` (B,) the pipeline's answers.
        training_k: (N, 8) the training split's true fault vectors, or None (no training split).
        read_training: reads the training split's clean records (len(rows), n_full) [A] at sorted row indices.
        noise: relative measurement noise added to the training records (the held-out records' own).
        seed: noise seed.
        drive_bound: the bundle's drive-range bound [A]: training records beyond it are left out, as held-out ones.

    Returns:
        ``signals`` (M, n_full), ``k_hat`` (M, 8), and the row counts ``held_out`` and ``training``.
    """
    rows = near_nominal_rows(pipeline, held_out.k, held_out.ood)
    signals, k_hat = held_out.signals[rows], held_out.k_hat[rows]
    n_held, n_train = int(rows.sum()), 0
    if n_held < NEAR_MIN_ROWS and training_k is not None and read_training is not None and len(training_k):
        near = no_large_fault(pipeline, training_k.to(pipeline.nominal.dtype))
        index = near.nonzero().flatten()[:TRAINING_ROWS_MAX].tolist()
        if index:
            clean = read_training(index)
            clean = clean[within_drive_range(clean, drive_bound)]
            x = noisy(clean, noise, seed + 1)
            with torch.no_grad():
                answer = pipeline(x.to(pipeline.times.dtype))
            keep = ~answer[3].to(torch.bool)
            signals = torch.cat([signals, x[keep].to(signals.dtype)])
            k_hat = torch.cat([k_hat, answer[0][keep].to(k_hat.dtype)])
            n_train = int(keep.sum())
        log.info(
            "near-nominal checks: %d held-out records near nominal in truth, below %d; %d of the training split's added",
            n_held,
            NEAR_MIN_ROWS,
            n_train,
        )
    if n_held + n_train < NEAR_MIN_ROWS:
        log.warning(
            "the near-nominal checks (shape, unexplained, spikes) are calibrated on %d records near nominal in truth "
            "(%d held-out, %d training), fewer than %d: their thresholds rest on a few records' extremes; a larger "
            "store (more val and train records) or a sampling nearer nominal (dataset.healthy_fraction) measures them",
            n_held + n_train,
            n_held,
            n_train,
            NEAR_MIN_ROWS,
        )
    return SimpleNamespace(signals=signals, k_hat=k_hat, held_out=n_held, training=n_train)
