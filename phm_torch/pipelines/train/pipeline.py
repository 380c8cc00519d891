"""The training pipeline: every surrogate from a dataset store, evaluated on its validation split.

Steps: POD of the training currents -> sample selection -> gappy POD layer -> FDI network (Lightning
Trainer: progress bar, CSV/TensorBoard logs, checkpoints; LM or Adam, optionally end to end) -> health
classifier (refined on the boundary with the store's own assessment) -> verdict classifier of the FDI
estimates -> forward surrogate -> evaluation on the validation split (clean, noisy, missing samples), latencies.

:func:`train_surrogates` is a plain function of :class:`~.settings.TrainSettings` and the injected
strategies (the sample selector, the classifier kind); ``phm-train`` (:mod:`phm_torch.apps.train`) composes the
config, calls it and writes what it returns.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import Any

import lightning as L
import torch

from ... import provenance
from ...data.store import recorded_actuator
from ...drive_range import within_drive_range
from ...surrogates import SurrogateBundle
from ...surrogates.classifiers.base import HealthClassifier
from ...surrogates.evaluate import evaluate_classifier, evaluate_fdi, measure_latency, quartiles
from ...surrogates.forward import fit_forward_check
from ...surrogates.full_signal_check import FullSignalCheck
from ...surrogates.metrics import err_k
from ...surrogates.ood_calibration import ood_thresholds, shape_thresholds
from ...surrogates.selectors.base import Selector
from .classifiers import fit_classifiers, store_labeller
from .data import Reduction, StoreData, fit_reduction, load_data
from .fdi import fit_fdi, make_loggers
from .settings import TrainSettings


def evaluate(
    settings: TrainSettings,
    data: StoreData,
    red: Reduction,
    network: Any,
    classifier: HealthClassifier,
    verdict: HealthClassifier | None,
    timing: dict[str, float],
) -> tuple[dict[str, Any], dict[str, Any], dict[str, float], Any]:
    """The forward surrogate (if asked) and every figure on the validation split: FDI errors (clean, noisy,
    missing samples), classifier and verdict confusion, latencies, OOD thresholds and rates.

    Returns:
        metrics, arrays (the validation predictions), the OOD thresholds (trained with ``eval.noise``) and the
        shares of val beyond them, the forward surrogate (None without one).
    """
    pod, gappy, seed, ev, val = red.pod, red.gappy, settings.seed, settings.eval, data.val
    params = recorded_actuator(data.info["metadata"])
    nominal = torch.tensor(params.nominal_faults) if params is not None else None
    forward = (
        fit_forward_check(pod, gappy, network, data.train.k, data.train.current, nominal, seed + 13)
        if settings.forward_check
        else None
    )
    metrics, arrays = evaluate_fdi(pod, gappy, network, val.current, val.k, ev.noise, ev.missing, seed, nominal)
    if data.current_bound is not None:  # err_k of the val records a protected drive would have finished
        inside = within_drive_range(val.current, data.current_bound)
        metrics["val_beyond_drive_range"] = int((~inside).sum())
        metrics["err_k_in_drive_range"] = err_k(arrays["k_hat"][inside], val.k[inside]) if bool(inside.any()) else None
    t0 = time.perf_counter()
    with torch.no_grad():
        network(gappy(red.samples_va)[0])
    timing["fdi_eval_per_signal_us"] = (time.perf_counter() - t0) / max(len(val), 1) * 1e6
    metrics.update(evaluate_classifier(classifier, val.k, val.healthy, arrays["k_hat"], verdict))
    metrics.update(measure_latency(gappy, network, classifier, red.samples_va, ev.latency_repeats))
    calibrating = data.train.current if data.inside is None else data.train.current[data.inside]
    base = FullSignalCheck(pod.modes_, pod.mean_)  # default thresholds: the statistics the calibrations read
    threshold, full_threshold = ood_thresholds(calibrating, gappy, base, ev.noise, ev.ood_quantile, seed + 7)
    rough, plateau = shape_thresholds(calibrating, base, ev.ood_quantile)
    check = FullSignalCheck(
        pod.modes_, pod.mean_, residual_threshold=full_threshold, roughness_threshold=rough, plateau_threshold=plateau
    )
    with torch.no_grad():  # report how much of the (clean) val records the full-record check rejects
        full_ood_val = float(check(val.current).double().mean()) if len(val) else float("nan")
    ood = {
        "ood_residual_threshold": threshold,
        "ood_rate_val": float((arrays["residual"] > threshold).float().mean()),
        "ood_full_residual_threshold": full_threshold,
        "ood_roughness_threshold": rough,
        "ood_plateau_threshold": plateau,
        "ood_full_rate_val": full_ood_val,
    }
    return metrics, arrays, ood, forward


def make_bundle(
    settings: TrainSettings,
    data: StoreData,
    red: Reduction,
    network: Any,
    selector: Selector,
    classifier: HealthClassifier,
    verdict: HealthClassifier | None,
    forward: Any,
    ood: dict[str, float],
    model_name: str,
) -> SurrogateBundle:
    """The :class:`SurrogateBundle` the online pipeline loads: the reduction, the FDI network, the classifiers,
    the OOD thresholds, the forward surrogate, and what it was made from (store fingerprint, seed, provenance)."""
    return SurrogateBundle(
        red.pod,
        selector.indices_,
        network,
        classifier,
        data.sample_rate,
        ood["ood_residual_threshold"],
        settings.gappy.ridge,
        selector={"name": selector.name, "params": selector.get_params()},
        meta={
            "data_fingerprint": data.info["manifest"].get("fingerprint"),
            "seed": settings.seed,
            "model": model_name,
            "n_train": len(data.train),
            "provenance": data.provenance,
            "drive_current_bound": data.current_bound,
            "assessment": (data.info["metadata"].get("config") or {}).get("assessment"),  # the labels' phi_a
        },
        full_residual_threshold=ood["ood_full_residual_threshold"],
        roughness_threshold=ood["ood_roughness_threshold"],
        plateau_threshold=ood["ood_plateau_threshold"],
        gappy_statistics=red.statistics,
        nominal_record=data.info["nominal"],
        verdict_classifier=verdict,
        forward_model=forward,
    )


def train_surrogates(
    settings: TrainSettings, selector: Selector, make_classifier: Callable[[], HealthClassifier]
) -> tuple[dict[str, Any], dict[str, Any]]:
    """Train every surrogate from the store ``settings.data_dir`` and evaluate it on the validation split.

    Args:
        settings: the run's settings.  selector: the sample-time selector (unfitted).
        make_classifier: returns an unfitted classifier of the chosen kind (called for the health classifier
            and again for the verdict classifier).

    Returns:
        ``metrics`` (errors and rates are fractions) and ``objects``: ``bundle`` (:class:`SurrogateBundle`),
        ``pod``, ``selector``, ``module`` (the FDIModule), ``trainer``, ``arrays`` (validation predictions),
        ``out_dir``. On the non-zero ranks of a multi-device run: ``({}, {"trainer": trainer})``.
    """
    classifier = make_classifier()
    loggers = make_loggers(settings.loggers, settings.out_dir)
    seed = settings.seed
    L.seed_everything(seed, workers=True, verbose=False)
    timing: dict[str, float] = {}
    data = load_data(settings, timing)
    labeller = store_labeller(settings, data.info["metadata"])
    red = fit_reduction(settings, selector, data, timing)
    fdi = fit_fdi(settings, data, red, loggers, timing)
    if not fdi.trainer.is_global_zero:
        return {}, {"trainer": fdi.trainer}
    network, module = fdi.network, fdi.module
    n_classifier, refine_info, verdict = fit_classifiers(
        settings, classifier, make_classifier, data, red, network, labeller, timing, (fdi.fit_rows, fdi.monitor_rows)
    )
    metrics, arrays, ood, forward = evaluate(settings, data, red, network, classifier, verdict, timing)
    pod, gappy, info = red.pod, red.gappy, data.info
    fingerprint = info["manifest"].get("fingerprint")
    model_name = module.optimizer_name + ("_e2e" if settings.model.end_to_end else "")
    metrics.update(
        n_train=len(data.train),
        drive_current_bound=data.current_bound,
        n_train_beyond_drive_range=data.beyond_range,
        n_fdi_fit=len(fdi.fit_rows),
        n_fdi_monitor=0 if fdi.monitor_rows is None else len(fdi.monitor_rows),
        n_val=len(data.val),
        n_modes=settings.n_modes,
        n_points=settings.n_points,
        n_hidden=settings.n_hidden,
        n_layers=settings.n_layers,
        n_members=settings.n_members,
        selector=selector.name,
        selector_params=selector.get_params(),
        selector_fallback=getattr(selector, "fallback_", None),  # the SOM's points replaced (ill-conditioned)
        classifier=classifier.name,
        gappy_estimator=settings.gappy.estimator,
        forward_check=forward.summary() if forward else None,
        model=model_name,
        fdi_inputs=settings.model.fit.inputs,
        classifier_threshold=float(classifier.threshold),
        n_classifier_train=n_classifier,
        classifier_refine={k: v for k, v in refine_info.items() if k != "verdict_calibration"},
        verdict_calibration=refine_info.get("verdict_calibration"),
        energy_retained=float(pod.cumulative_energy()[settings.n_modes - 1]),
        gappy_condition_number=gappy.condition_number(),
        **ood,
        eval_noise=settings.eval.noise,
        eval_missing=settings.eval.missing,
        best_epoch=fdi.keep.best_epoch,
        epochs_run=fdi.trainer.current_epoch,
        sample_rate=data.sample_rate,
        data_dir=settings.data_dir,
        data_fingerprint=fingerprint,
        timing={k: round(v, 4) for k, v in timing.items()},
        seed=seed,
        actuator=provenance.describe(data.provenance["actuator"]),
        command=provenance.describe(data.provenance["command"]),
    )
    err = quartiles(arrays["err_alpha"])
    metrics.update(err_alpha_q1=err["q1"], err_alpha_q3=err["q3"])

    bundle = make_bundle(settings, data, red, network, selector, classifier, verdict, forward, ood, model_name)
    with torch.no_grad():
        arrays.update(
            healthy=data.val.healthy,
            score=bundle.health_score(data.val.k),
            score_chain=bundle.verdict_score(arrays["k_hat"]),
            indices=selector.indices_,
            time=data.grid,
            mode_1=pod.modes_[:, 0],
            energy=pod.energy_,
        )
    return metrics, {
        "bundle": bundle,
        "pod": pod,
        "selector": selector,
        "module": module,
        "trainer": fdi.trainer,
        "arrays": arrays,
        "out_dir": settings.out_dir,
    }
