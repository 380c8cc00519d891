"""The assessment-only ``labels`` split: extra fault vectors labelled by phi_a, without HF signals.

The health classifier learns from (k, healthy) pairs; a label costs one assessment (~2.5 ms per vector,
batched) where a training row also costs an HF simulation, so the store can hold many more labels than
signals (``dataset.n_labels``; classifier accuracy ~97 % with 10k labelled vectors, ~99 % with ~50k).

The ``n_labels`` fault vectors are importance-sampled on the full domain like ``train``, from their own
seed stream (child 3 of ``SeedSequence(seed)``: the train/val/rul streams are unchanged by it). They form
a row list of their own, cut into ``ceil(n_labels / label_chunk_size)`` chunks of equal size (the last
padded with k_0 rows, dropped before writing, so every assessment batch has the same size and a compiled
simulator compiles once); chunk j is ``chunks/labels_0000j.h5`` (``LABEL_CHUNKS``), owned by shard
``j % shard_count``, computed, verified and merged by the functions of ``generation.py``.
"""

from __future__ import annotations

import math
import time
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np
import torch

from ..assessment import AssessmentFunction
from .generation import Plan, seed_record, seed_streams
from .sampling import ImportanceSampler
from .spec import DatasetSpec
from .store import LABEL_CHUNKS, LABELS


def label_chunk_rows(n_labels: int, label_chunk_size: int) -> int:
    """Rows per labels chunk: ``n_labels`` spread evenly over ceil(n_labels / label_chunk_size) chunks
    (at most ``label_chunk_size``; padding at most one row per chunk but the first)."""
    n_chunks = math.ceil(n_labels / label_chunk_size)
    return math.ceil(n_labels / n_chunks)


def make_label_plan(
    spec: DatasetSpec, nominal: Sequence[float], seed: int, sampling: Mapping[str, Any] | None = None
) -> Plan | None:
    """The labels split's row list: K (n_labels, 8) from the full-domain importance sampler (with the calibrated
    ``sampling`` record, as train) and the ``labels`` seed stream; None when ``spec.n_labels`` is 0 (the store then
    has no labels split)."""
    streams = seed_streams(seed)
    if spec.n_labels == 0:
        return None
    full = ImportanceSampler.from_record(sampling, nominal, spec.uniform)
    k = full.sample(spec.n_labels, streams[LABELS])
    rows = label_chunk_rows(spec.n_labels, spec.label_chunk_size)
    return Plan(k, {LABELS: (0, spec.n_labels)}, rows, seed_record({LABELS: streams[LABELS]}), LABEL_CHUNKS)


class LabelComputer:
    """Computes the arrays of one labels chunk: phi_a of its fault vectors (no simulator signals).

    Args:
        assessment: phi_a.
        nominal: k_0 (8,), the padding rows.
        chunk_size: the batch size (``Plan.chunk_size`` of the labels plan); shorter chunks are padded.
    """

    def __init__(self, assessment: AssessmentFunction, nominal: Sequence[float], chunk_size: int):
        self.assessment = assessment
        self.nominal = np.asarray(nominal, dtype=np.float64)
        self.chunk_size = int(chunk_size)
        self.timing = {"labels_s": 0.0}
        self.vectors = 0  # fault vectors assessed, padding included

    def __call__(self, k: np.ndarray) -> dict[str, np.ndarray]:
        """K (m, 8) -> {"K" (m, 8) float64, "healthy" (m,) uint8, "margins" (m, 5) float64}."""
        m = k.shape[0]
        pad = np.repeat(self.nominal[None], self.chunk_size - m, axis=0)
        kt = torch.as_tensor(np.concatenate([k, pad]), dtype=torch.float64)
        t0 = time.perf_counter()
        res = self.assessment(kt)
        self.timing["labels_s"] += time.perf_counter() - t0
        self.vectors += kt.shape[0]
        return {
            "K": k.astype(np.float64),
            "healthy": res.healthy[:m].numpy().astype(np.uint8),
            "margins": res.margins.stacked()[:m].numpy(),
        }
