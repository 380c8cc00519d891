"""The training pipeline's classifiers: the health classifier on k (refined on its boundary with the store's
own assessment, calibrated to a missed-fault rate) and the verdict classifier on the FDI estimates."""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import Any

import numpy as np
import torch

from ...checks import build
from ...data.labels import LabelComputer, label_chunk_rows
from ...data.life import LifeSpec
from ...data.sampling import ImportanceSampler
from ...data.spec import DatasetSpec
from ...data.store import LABELS, read_labelled, recorded_assessment
from ...surrogates import rms
from ...surrogates.classifiers.base import HealthClassifier
from ...surrogates.classifiers.damage_paths import DamagePathSampler
from ...surrogates.classifiers.refinement import refine_classifier
from ...surrogates.verdict_classifier import calibrate_verdict_held_out, fit_verdict_classifier, noisy_estimates
from .data import Reduction, StoreData
from .settings import TrainSettings

REFINE_STREAM = 0x5EF1  # seed-sequence key of the classifier refinement's candidates
PATH_STREAM = 0x9A7  # offset of the damage-law path candidates' seed
Sampler = Callable[[int, int], Any]
Assessor = Callable[[Any], Any]


def classifier_set(
    settings: TrainSettings, k: torch.Tensor, healthy: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """The health classifier's training set: the train split's (k (N, 8) as float64, healthy (N,)) and, with
    ``settings.classifier_labels``, the store's assessment-only ``labels`` split (if it has one)."""
    k = k.to(torch.float64)
    if not settings.classifier_labels:
        return k, healthy
    k_extra, h_extra = read_labelled(settings.data_dir, splits=(LABELS,), optional=(LABELS,))
    return (torch.cat([k, torch.from_numpy(k_extra)]), torch.cat([healthy, torch.from_numpy(h_extra)]))


def store_labeller(
    settings: TrainSettings, metadata: dict[str, Any]
) -> tuple[Sampler | None, Assessor | None, Sampler | None]:
    """The classifier refinement's candidate sampler, labeller phi_a and damage-law path sampler, rebuilt from the
    config the store records (its actuator, assessment and importance sampler), so that the new labels are the
    store's own kind, and from ``settings.damage`` (the paths); ``(None, None, None)`` without refinement
    rounds, no path sampler without path labels."""
    rounds = settings.refine.rounds
    if rounds == 0:
        return None, None, None
    config = metadata.get("config") or {}
    if "actuator" not in config or "assessment" not in config or "dataset" not in config:
        raise ValueError(
            f"classifier_refine.rounds={rounds}: the store {settings.data_dir!r} does not record "
            f"the actuator, assessment and dataset config its labels were made with; set "
            f"classifier_refine.rounds=0"
        )
    assessment, params = recorded_assessment(metadata, settings.refine_device)
    dataset = config["dataset"]
    # candidates drawn as the store's training vectors were: with its calibrated radial law
    sampler = ImportanceSampler.from_record(metadata.get("sampling"), params.nominal_faults, dataset.get("uniform", []))
    chunk = int(dataset.get("label_chunk_size", DatasetSpec.label_chunk_size))
    seed = settings.seed

    def sample(n: int, r: int) -> Any:
        return sampler.sample(n, np.random.SeedSequence([seed, REFINE_STREAM, r]))

    def assess(k: Any) -> Any:  # equal batches, as phm-generate's labels split (one compiled shape)
        rows = label_chunk_rows(len(k), chunk)
        labeller = LabelComputer(assessment, params.nominal_faults, rows)
        return np.concatenate([labeller(k[i : i + rows])["healthy"] for i in range(0, len(k), rows)]).astype(bool)

    paths = None
    if settings.refine.path_labels_per_round > 0 and settings.damage is not None:
        law = build(settings.damage, "damage", nominal=list(params.nominal_faults))
        # initial damage as the store's life split draws it (the same default when it has none)
        initial = (dataset.get("life") or {}).get("initial_damage", LifeSpec.initial_damage)
        paths = DamagePathSampler(law, float(initial), sampler.uniform, seed + PATH_STREAM).sample
    return sample, assess, paths


def fit_health_classifier(
    settings: TrainSettings,
    classifier: HealthClassifier,
    k: torch.Tensor,
    healthy: torch.Tensor,
    labeller: tuple[Sampler | None, Assessor | None, Sampler | None],
    fingerprint: str | None,
    timing: dict[str, float],
) -> tuple[int, dict[str, Any]]:
    """Fit the health classifier on the training split's (k (N, 8), healthy (N,)) and the store's labels split
    (:func:`classifier_set`), refined on its boundary with ``labeller`` (:func:`store_labeller`) and calibrated
    to ``settings.max_missed_fault_rate``; returns the number of vectors it was fitted on and the refinement's
    report (timings into ``timing``). ``fingerprint`` (the store's) keys the refinement's label cache."""
    t0 = time.perf_counter()
    k_cls, healthy_cls = classifier_set(settings, k, healthy)
    sample, assess, sample_paths = labeller
    k_all, _, refine_info = refine_classifier(
        classifier,
        k_cls,
        healthy_cls,
        sample,
        assess,
        settings.refine,
        settings.seed,
        settings.out_dir / "classifier_labels",
        {"data": fingerprint, "damage": settings.damage},
        sample_paths,
        labels_of=fingerprint,  # the store's fingerprint fixes its recorded phi_a
    )
    if settings.max_missed_fault_rate is not None:  # on the importance-sampled set: the refined one crowds the boundary
        classifier.calibrate(k_cls, healthy_cls, settings.max_missed_fault_rate)
    timing["classifier_fit_s"] = time.perf_counter() - t0 - refine_info["assess_s"]
    timing["classifier_refine_assess_s"] = refine_info["assess_s"]
    return len(k_all), refine_info


def fit_classifiers(
    settings: TrainSettings,
    classifier: HealthClassifier,
    make_classifier: Callable[[], HealthClassifier],
    data: StoreData,
    red: Reduction,
    network: Any,
    labeller: tuple[Sampler | None, Assessor | None, Sampler | None],
    timing: dict[str, float],
    fdi_rows: tuple[torch.Tensor, torch.Tensor | None] | None = None,
) -> tuple[int, dict[str, Any], HealthClassifier | None]:
    """Fit the health classifier on k (refined on its boundary with the store's assessment, calibrated to
    ``max_missed_fault_rate``) and, with ``settings.verdict_classifier``, a fresh one on the FDI estimates of the
    training records with ``eval.noise`` (the verdict on a measured actuator).

    ``fdi_rows``: the training rows that fitted the FDI and those held out from it (monitor rows; None without);
    with ``settings.verdict_max_missed_fault_rate`` the verdict is fitted on the former and calibrated on the
    latter's estimates, which err as an unseen record's do (:func:`calibrate_verdict_held_out`).

    Returns:
        the number of vectors the health classifier was fitted on, the refinement's report (with
        ``verdict_calibration`` when calibrated), the verdict classifier (None without one).
    """
    train, seed, max_missed = data.train, settings.seed, settings.max_missed_fault_rate
    n_fitted, refine_info = fit_health_classifier(
        settings, classifier, train.k, train.healthy, labeller, data.info["manifest"].get("fingerprint"), timing
    )
    verdict = None
    if settings.verdict_classifier:  # judges estimates: fitted on the training records' own, with eval.noise
        t0 = time.perf_counter()
        gappy = red.gappy

        def estimate(s: torch.Tensor, level: torch.Tensor) -> torch.Tensor:
            return network(gappy(s)[0], level)

        held_out = settings.verdict_max_missed_fault_rate is not None
        if held_out and (fdi_rows is None or fdi_rows[1] is None):
            raise ValueError(
                "calibration.verdict_max_missed_fault_rate needs the FDI's monitor rows (monitor_fraction > 0)"
            )
        rows = fdi_rows[0] if held_out else slice(None)
        current, healthy = train.current[rows], train.healthy[rows]
        verdict = fit_verdict_classifier(
            make_classifier(),
            estimate,
            red.samples_tr[rows],
            rms(current),
            healthy,
            settings.eval.noise,
            seed + 11,
            None if held_out else max_missed,
        )
        if held_out:
            monitor = fdi_rows[1]
            refine_info["verdict_calibration"] = calibrate_verdict_held_out(
                verdict,
                noisy_estimates(
                    estimate, red.samples_tr[monitor], rms(train.current[monitor]), settings.eval.noise, seed + 13
                ),
                train.healthy[monitor],
                settings.verdict_max_missed_fault_rate,
            )
        timing["verdict_classifier_fit_s"] = time.perf_counter() - t0
    return n_fitted, refine_info, verdict
