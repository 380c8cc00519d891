"""Give a trained surrogate bundle a verdict classifier fitted on its own FDI estimates, without retraining.

``phm-train`` fits one (``verdict_classifier=true``, the default) right after the FDI network;
:func:`refit_verdict_classifier` does the same for a bundle that lacks one (or replaces it), from the store the
bundle was trained on: the selected samples of every record of a split, white noise of ``noise`` times each
record's RMS current (the rated measurement noise, phm-train's ``eval.noise``), the bundle's FDI told that
level, and a classifier of the bundle's own kind and settings fitted on (k_hat, the records' health)
(:mod:`.verdict_classifier`). The split is read in row blocks, so an 80,000-record store needs little memory.
``scripts/fit_verdict_classifier.py`` is the command line.
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

import numpy as np
import torch

from ..data.store import DatasetStore
from .augment import rms
from .bundle import SurrogateBundle
from .classifiers import build_classifier
from .metrics import confusion
from .verdict_classifier import fit_verdict_classifier

BLOCK = 4000  # records read at a time


def read_samples(bundle: SurrogateBundle, data_dir: str, split: str) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Selected samples (N, n_w) [A], RMS currents (N,) [A] and health (N,) bool of a split's records."""
    samples, scale, healthy = [], [], []
    with DatasetStore(data_dir) as store:
        bundle.check_store(store.provenance, f"store {data_dir}")
        view = store.split(split)  # a ValueError naming the store's splits if it has no such split
        for start in range(0, len(view), BLOCK):
            x = torch.as_tensor(np.asarray(view.current[start : start + BLOCK]), dtype=bundle.pod.mean_.dtype)
            samples.append(bundle.compress(x))
            scale.append(rms(x))
            healthy.append(torch.as_tensor(np.asarray(view.healthy[start : start + BLOCK])).bool())
    if not samples:
        raise ValueError(f"split {split!r} of {data_dir!r} is empty")
    return torch.cat(samples), torch.cat(scale), torch.cat(healthy)


@torch.no_grad()
def verdicts(bundle: SurrogateBundle, data_dir: str, split: str) -> dict[str, dict[str, float]]:
    """Confusion of the health classifier and of the verdict on the FDI estimates of a split's records
    (the FDI told each record's estimated noise level, as the online pipeline does)."""
    k_hat, healthy = [], []
    with DatasetStore(data_dir) as store:
        view = store.split(split)
        for start in range(0, len(view), BLOCK):
            x = torch.as_tensor(np.asarray(view.current[start : start + BLOCK]), dtype=bundle.pod.mean_.dtype)
            k_hat.append(bundle.estimate(x))
            healthy.append(torch.as_tensor(np.asarray(view.healthy[start : start + BLOCK])).bool())
    k_hat, healthy = torch.cat(k_hat), torch.cat(healthy)
    keys = ("accuracy", "missed_fault_rate", "false_alarm_rate")
    return {
        name: {k: v for k, v in confusion(pred, healthy).items() if k in keys}
        for name, pred in (
            ("health_classifier", bundle.is_healthy(k_hat)),
            ("verdict", bundle.verdict_healthy(k_hat)),
        )
    }


def refit_verdict_classifier(
    bundle_path: str | Path,
    data_dir: str,
    out: str | Path,
    split: str = "train",
    check_split: str = "val",
    noise: float = 0.01,
    seed: int = 11,
    max_missed_fault_rate: float | None = None,
) -> dict[str, Any]:
    """Fit the verdict classifier of the bundle at ``bundle_path`` on ``split`` of its store and save the bundle
    with it at ``out``.

    Args:
        bundle_path: the SurrogateBundle to read.  data_dir: the store it was trained on.
        out: where to write the bundle with its verdict classifier.
        split: records the verdict classifier is fitted on.
        check_split: records the verdicts are reported on (``""``: none).
        noise: relative current noise of the fitting records (>= 0).  seed: seeds the noise draw.
        max_missed_fault_rate: None, or raise the verdict threshold until at most this fraction of the
            fitting faults pass.
    Returns:
        The report: inputs, ``n`` fitting records, ``fit_s`` [s], and ``{check_split: verdicts(...)}``.
    """
    if not noise >= 0:
        raise ValueError(f"noise must be >= 0, got {noise!r}")
    bundle = SurrogateBundle.load(bundle_path)
    t0 = time.perf_counter()
    samples, scale, healthy = read_samples(bundle, data_dir, split)
    spec = bundle.classifier
    bundle.verdict_classifier = fit_verdict_classifier(
        build_classifier(spec.name, **spec.get_params()),
        lambda s, level: bundle.fdi(s, noise=level),
        samples,
        scale,
        healthy,
        noise,
        seed,
        max_missed_fault_rate,
    )
    fit_s = time.perf_counter() - t0
    bundle.save(out)
    report = {
        "bundle": bundle_path,
        "out": out,
        "split": split,
        "n": len(healthy),
        "noise": noise,
        "max_missed_fault_rate": max_missed_fault_rate,
        "fit_s": round(fit_s, 1),
    }
    if check_split:
        report[check_split] = verdicts(bundle, data_dir, check_split)
    return report
