"""``phm-train``: learn the surrogates from a dataset store; write metrics.json and the SurrogateBundle.

Examples::

    phm-train                                                   # store data/quick, the paper's choices
    phm-train data_dir=data/paper out_dir=results/paper
    phm-train model=fdi_e2e selector=greedy n_points=40
    phm-train -m experiment=ablation_hidden data_dir=data/paper # Hydra multirun sweep

Steps: POD of the training currents -> sample selection -> gappy POD layer -> FDI network (Lightning
Trainer: progress bar, CSV/TensorBoard logs, checkpoints; LM or Adam, optionally end to end) -> health
classifier -> verdict classifier of the FDI estimates -> evaluation on the validation split (clean, noisy,
missing samples), latencies.
The work is done by :func:`train_surrogates` (a plain function of the composed config);
:func:`main` is the thin Hydra entry point.
"""

from __future__ import annotations

import json
import logging
import time
from functools import partial
from pathlib import Path
from typing import Any

import hydra
import lightning as L
import numpy as np
import torch
from hydra.errors import InstantiationException
from hydra.utils import instantiate
from omegaconf import DictConfig
from torch.utils.data import DataLoader, TensorDataset

from .. import provenance
from ..data.labels import LabelComputer, label_chunk_rows
from ..data.sampling import ImportanceSampler
from ..data.store import LABELS, metadata_provenance, read_labelled
from ..io.atomic import atomic_open
from ..surrogates import POD, GappyPOD, SurrogateBundle, build_fdi_network, rms
from ..surrogates.classifiers.refinement import BoundaryRefinement, refine_classifier
from ..surrogates.data import load_store
from ..surrogates.evaluate import evaluate_classifier, evaluate_fdi, measure_latency, quartiles
from ..surrogates.forward import fit_forward_check
from ..surrogates.full_signal_check import FullSignalCheck
from ..surrogates.gappy_pod import gappy_statistics
from ..surrogates.lightning_fdi import NOISE_INPUT_NEEDS, FDIModule, KeepBest
from ..surrogates.ood_calibration import ood_thresholds
from ..surrogates.verdict_classifier import fit_verdict_classifier
from . import common

log = logging.getLogger(__name__)

LOGGERS = ("csv", "tensorboard")
REFINE_STREAM = 0x5EF1   # seed-sequence key of the classifier refinement's candidates
INPUTS = ("gappy", "full")
ESTIMATORS = ("least_squares", "bayesian")


def _instantiate(node: Any, name: str, **kwargs: Any) -> Any:
    """Instantiate a config node; a constructor error is reported as ``name: ...``."""
    try:
        return instantiate(node, **kwargs)
    except InstantiationException as e:
        cause = e.__cause__ if e.__cause__ is not None else e
        raise ValueError(f"{name}: {cause}") from None


def _loggers(cfg: DictConfig, out_dir: Path) -> list[Any]:
    names = common.plain(cfg.get("loggers")) or []
    if not isinstance(names, list) or any(n not in LOGGERS for n in names):
        raise ValueError(f"loggers must be a list drawn from {list(LOGGERS)}, got {names!r}")
    out: list[Any] = []
    if "csv" in names:
        out.append(L.pytorch.loggers.CSVLogger(out_dir, name="logs"))
    if "tensorboard" in names:
        try:
            out.append(L.pytorch.loggers.TensorBoardLogger(out_dir, name="tensorboard"))
        except ModuleNotFoundError as e:
            raise ValueError(f"loggers: tensorboard needs the tensorboard package "
                             f"(pip install -e '.[tensorboard]'): {e}") from None
    return out


def _fit_settings(cfg: DictConfig) -> dict[str, Any]:
    fit = common.plain(cfg.model.get("fit")) or {}
    out = {"max_epochs": common.integer(fit.get("max_epochs"), "model.fit.max_epochs", 1),
           "patience": common.integer(fit.get("patience"), "model.fit.patience", 1),
           "batch_size": None if fit.get("batch_size") is None else common.integer(fit["batch_size"],
                                                                                   "model.fit.batch_size", 1),
           "inputs": fit.get("inputs", "gappy")}
    if out["inputs"] not in INPUTS:
        raise ValueError(f"model.fit.inputs must be one of {list(INPUTS)}, got {out['inputs']!r}")
    return out


def _monitor_rows(n: int, fraction: float, seed: int) -> tuple[torch.Tensor, torch.Tensor | None]:
    """Rows of the training split that fit the FDI network and rows held out to choose its epoch.

    The epoch (early stopping, best weights) is chosen on signals the network never trains on and
    that are not the reported ``val`` split, so the ``val`` figures are not tuned on (MATLAB's trainlm
    divides its data the same way). ``fraction = 0`` keeps every row for fitting and returns ``None``:
    the epoch is then chosen on ``val`` itself (optimistic by a few tenths of a point of err_k).
    """
    if fraction == 0.0:
        return torch.arange(n), None
    n_monitor = max(1, round(fraction * n))
    if n - n_monitor < 2:
        raise ValueError(f"monitor_fraction={fraction} leaves {n - n_monitor} of {n} training signals to fit")
    perm = torch.randperm(n, generator=torch.Generator().manual_seed(seed + 0x3011))
    return perm[n_monitor:].sort().values, perm[:n_monitor].sort().values


def _module_factory(cfg: DictConfig) -> partial:
    node = {k: v for k, v in common.plain(cfg.model).items() if k not in ("fit", "end_to_end", "network")}
    return _instantiate(node, "model", _partial_=True)


def _out_dir(cfg: DictConfig) -> Path:
    """``out_dir``, except in a Hydra multirun, where every job writes into its own sweep subdirectory."""
    from hydra.core.hydra_config import HydraConfig
    from hydra.types import RunMode

    if HydraConfig.initialized() and HydraConfig.get().mode == RunMode.MULTIRUN:
        return Path(HydraConfig.get().runtime.output_dir)
    return Path(str(cfg.out_dir)).expanduser()


def _save_tensors(path: Path, tensors: dict[str, torch.Tensor]) -> None:
    with atomic_open(path, "wb") as fh:
        torch.save({k: v.detach().cpu() for k, v in tensors.items()}, fh)


def _classifier_set(cfg: DictConfig, train: Any) -> tuple[torch.Tensor, torch.Tensor]:
    """The health classifier's training set: the train split's (k, label) and, unless
    ``classifier_labels`` is false, the store's assessment-only ``labels`` split (if it has one)."""
    k, healthy = train.k.to(torch.float64), train.healthy
    if not bool(cfg.classifier_labels):
        return k, healthy
    k_extra, h_extra = read_labelled(str(cfg.data_dir), splits=(LABELS,), optional=(LABELS,))
    return (torch.cat([k, torch.from_numpy(k_extra)]), torch.cat([healthy, torch.from_numpy(h_extra)]))


def _refinement(cfg: DictConfig, metadata: dict[str, Any], seed: int) -> tuple[BoundaryRefinement, Any, Any]:
    """The classifier refinement's settings, candidate sampler and labeller phi_a, both rebuilt from the
    config the store records (its actuator, assessment and importance sampler), so that the new labels
    are the store's own kind."""
    node = cfg.classifier_refine
    settings = BoundaryRefinement(node.rounds, node.labels_per_round, node.candidates_per_label)
    if settings.rounds == 0:
        return settings, None, None
    store_cfg = DictConfig(metadata.get("config") or {})
    if "actuator" not in store_cfg or "assessment" not in store_cfg or "dataset" not in store_cfg:
        raise ValueError(f"classifier_refine.rounds={settings.rounds}: the store {cfg.data_dir!r} does not record "
                         f"the actuator, assessment and dataset config its labels were made with; set "
                         f"classifier_refine.rounds=0")
    params = common.actuator(store_cfg)
    # candidates drawn as the store's training vectors were: with its calibrated distance exponent
    exponent = float((metadata.get("sampling") or {}).get("distance_exponent", 1.0))
    sampler = ImportanceSampler(tuple(params.nominal_faults), tuple(store_cfg.dataset.get("uniform", [])), 1.0,
                                distance_exponent=exponent)
    assessment = common.build(store_cfg.assessment, "assessment", params=params,
                              device=common.device(node.device))
    chunk = int(store_cfg.dataset.get("label_chunk_size", 4096))

    def sample(n: int, r: int) -> Any:
        return sampler.sample(n, np.random.SeedSequence([seed, REFINE_STREAM, r]))

    def assess(k: Any) -> Any:   # equal batches, as phm-generate's labels split (one compiled shape)
        rows = label_chunk_rows(len(k), chunk)
        labeller = LabelComputer(assessment, params.nominal_faults, rows)
        return np.concatenate([labeller(k[i:i + rows])["healthy"] for i in range(0, len(k), rows)]).astype(bool)

    return settings, sample, assess


def train_surrogates(cfg: DictConfig) -> tuple[dict[str, Any], dict[str, Any]]:
    """Train every surrogate from the store ``cfg.data_dir`` and evaluate it on the validation split.

    Returns:
        ``metrics`` (also written to ``out_dir/metrics.json``; errors and rates are fractions) and
        ``objects``: ``bundle`` (:class:`SurrogateBundle`, saved as ``out_dir/surrogates.pt``), ``pod``,
        ``selector``, ``module`` (the FDIModule), ``trainer``, ``arrays`` (validation predictions, saved
        as ``out_dir/predictions.pt``), ``out_dir``.
    """
    common.set_threads(cfg)
    seed = common.integer(cfg.seed, "seed", 0)
    n_modes = common.integer(cfg.n_modes, "n_modes", 1)
    n_points = common.integer(cfg.n_points, "n_points", 1)
    n_hidden = common.integer(cfg.n_hidden, "n_hidden", 1)
    n_layers = common.integer(cfg.n_layers, "n_layers", 1)
    n_members = common.integer(cfg.n_members, "n_members", 1)
    if n_members > 1 and cfg.model.get("optimizer") == "lm":
        raise ValueError(f"n_members={n_members} needs model=fdi_adam or model=fdi_e2e (LM trains one network)")
    network_kwargs = common.plain(cfg.model.get("network")) or {}
    for key in ("n_inputs", "n_hidden", "n_layers", "n_members"):
        if key in network_kwargs:
            raise ValueError(f"model.network.{key}: set the top-level {key} instead (one home per value)")
    for key, home in (("default_noise", "eval.noise"), ("max_noise", "model.augment.noise")):
        if key in network_kwargs:
            raise ValueError(f"model.network.{key}: it is {home} (one home per value)")
    ridge = common.number(cfg.gappy.ridge, "gappy.ridge", 0.0)
    estimator = str(cfg.gappy.estimator)
    if estimator not in ESTIMATORS:
        raise ValueError(f"gappy.estimator must be one of {list(ESTIMATORS)}, got {estimator!r}")
    if n_points < n_modes and ridge == 0.0 and estimator == "least_squares":
        raise ValueError(f"n_points={n_points} < n_modes={n_modes}: the gappy system is underdetermined "
                         f"(choose n_points >= n_modes, gappy.ridge > 0 or gappy.estimator=bayesian)")
    noise = common.number(cfg.eval.noise, "eval.noise", 0.0)
    missing = common.integer(cfg.eval.missing, "eval.missing", 0)
    ood_q = common.number(cfg.eval.ood_quantile, "eval.ood_quantile", 0.0)
    repeats = common.integer(cfg.eval.latency_repeats, "eval.latency_repeats", 1)
    max_missed = cfg.get("calibration", {}).get("max_missed_fault_rate")
    if max_missed is not None:
        max_missed = common.number(max_missed, "calibration.max_missed_fault_rate", 0.0)
    fit = _fit_settings(cfg)
    monitor_fraction = common.number(cfg.get("monitor_fraction", 0.0), "monitor_fraction", 0.0)
    if monitor_fraction >= 0.5:
        raise ValueError(f"monitor_fraction must be < 0.5 (a fraction of the training signals), got {monitor_fraction!r}")
    end_to_end = bool(cfg.model.get("end_to_end", False))
    make_module = _module_factory(cfg)
    selector = _instantiate(cfg.selector, "selector")
    classifier = _instantiate(cfg.classifier, "classifier")
    out_dir = _out_dir(cfg)
    loggers = _loggers(cfg, out_dir)
    splits = {k: str(v) for k, v in common.plain(cfg.splits).items()}
    if set(splits) != {"train", "val"}:
        raise ValueError(f"splits must map exactly the roles train and val to split names, got {splits}")
    limits = {k: (None if v is None else common.integer(v, f"limit.{k}", 1))
              for k, v in (common.plain(cfg.get("limit")) or {}).items()}
    L.seed_everything(seed, workers=True, verbose=False)
    timing: dict[str, float] = {}

    t0 = time.perf_counter()
    data, grid, info = load_store(str(cfg.data_dir), splits, limits)
    train, val = data["train"], data["val"]
    prov = common.reconcile_provenance(cfg, metadata_provenance(info["metadata"]), f"store {cfg.data_dir}")
    refine, sample, assess = _refinement(cfg, info["metadata"], seed)
    dt = torch.diff(grid)
    if not bool((dt > 0).all()) or float(dt.max() - dt.min()) > 1e-6 * float(dt.mean()):
        raise ValueError(f"store {cfg.data_dir!r}: time grid is not uniform")
    sample_rate = 1.0 / float(dt.mean())
    if len(train) <= n_modes:
        raise ValueError(f"n_modes={n_modes} needs more than {n_modes} training signals, the store has {len(train)}")
    timing["load_s"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    pod = POD(n_modes, solver=str(cfg.pod.solver), seed=seed).fit(train.current)
    timing["pod_fit_s"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    if selector.needs_snapshots:
        selector.fit(pod.modes_, grid, snapshots=train.current, mean=pod.mean_)
    else:
        selector.fit(pod.modes_, grid)
    timing["selector_fit_s"] = time.perf_counter() - t0
    statistics = None
    if estimator == "bayesian":   # the rated measurement noise (eval.noise of the median RMS current) joins R
        noise_std = noise * float(rms(train.current).median())
        statistics = gappy_statistics(train.current, pod.modes_, pod.mean_, selector.indices_, noise_std)
    gappy = GappyPOD(pod.modes_, pod.mean_, selector.indices_, ridge=ridge, **(statistics or {}))

    with torch.no_grad():
        samples_tr, samples_va = gappy.select(train.current), gappy.select(val.current)
        alpha_tr, _ = gappy(samples_tr)
        alpha_va, _ = gappy(samples_va)
        x_tr = alpha_tr if fit["inputs"] == "gappy" else pod(train.current)
    fit_rows, monitor_rows = _monitor_rows(len(train), monitor_fraction, seed)
    levels = None
    if network_kwargs.get("noise_input"):   # told each record's noise level, trained on levels in [0, augment.noise]
        max_noise = common.number((cfg.model.get("augment") or {}).get("noise", 0.0), "model.augment.noise", 0.0)
        if not end_to_end or max_noise <= 0:
            raise ValueError(NOISE_INPUT_NEEDS)     # before the module: the input scaling needs the range
        network_kwargs.update(default_noise=min(noise, max_noise), max_noise=max_noise)
        levels = torch.rand(len(fit_rows), generator=torch.Generator().manual_seed(seed + 3),
                            dtype=x_tr.dtype) * max_noise
    network = build_fdi_network(n_modes, n_hidden, n_layers, n_members, **network_kwargs)
    network.set_normalization(x_tr[fit_rows], levels)
    module: FDIModule = make_module(network=network, gappy=gappy if end_to_end else None)
    if module.optimizer_name == "lm":
        if fit["batch_size"] is not None:
            raise ValueError("model.fit.batch_size must be null for model.optimizer=lm (one full-batch step per epoch)")
        if int(cfg.trainer.devices) != 1 or int(cfg.trainer.num_nodes) != 1:
            raise ValueError("model.optimizer=lm runs on one device: set trainer.devices=1 and trainer.num_nodes=1")
    if end_to_end:
        tensors_tr = monitor_src = (samples_tr, train.k, rms(train.current))
        tensors_va = (samples_va, val.k, rms(val.current))
    else:   # monitored on gappy coefficients, as val is, whatever fit.inputs
        tensors_tr, monitor_src, tensors_va = (x_tr, train.k), (alpha_tr, train.k), (alpha_va, val.k)
    ds_tr = TensorDataset(*(t[fit_rows] for t in tensors_tr))
    ds_va = TensorDataset(*(tensors_va if monitor_rows is None else [t[monitor_rows] for t in monitor_src]))
    gen = torch.Generator().manual_seed(seed)
    batch = fit["batch_size"] or len(ds_tr)
    train_loader = DataLoader(ds_tr, batch_size=batch, shuffle=batch < len(ds_tr), generator=gen)
    val_loader = DataLoader(ds_va, batch_size=max(len(ds_va), 1))
    keep = KeepBest("val_err_k")
    callbacks = [keep, L.pytorch.callbacks.EarlyStopping("val_err_k", patience=fit["patience"], mode="min"),
                 L.pytorch.callbacks.ModelCheckpoint(out_dir / "checkpoints", monitor="val_err_k", mode="min",
                                                     save_last=True, filename="fdi-{epoch:04d}-{val_err_k:.5f}")]
    tcfg = common.plain(cfg.trainer)
    try:
        trainer = L.Trainer(max_epochs=fit["max_epochs"], logger=loggers or False, callbacks=callbacks,
                            default_root_dir=out_dir, log_every_n_steps=1, enable_model_summary=False, **tcfg)
    except (TypeError, ValueError, RuntimeError) as e:
        raise ValueError(f"trainer: {e}") from None
    ckpt = cfg.get("ckpt_path")
    if ckpt is not None and not Path(str(ckpt)).is_file():
        raise ValueError(f"ckpt_path {str(ckpt)!r} does not exist")
    t0 = time.perf_counter()
    trainer.fit(module, train_loader, val_loader, ckpt_path=None if ckpt is None else str(ckpt), weights_only=True)
    timing["fdi_train_s"] = time.perf_counter() - t0
    if not trainer.is_global_zero:
        return {}, {"trainer": trainer}
    keep.restore(module)
    module.cpu()                                   # the gappy layer too (it is a submodule end to end)
    network = module.network.float().eval()

    t0 = time.perf_counter()
    k_cls, healthy_cls = _classifier_set(cfg, train)
    k_all, _, refine_info = refine_classifier(classifier, k_cls, healthy_cls, sample, assess, refine, seed,
                                              out_dir / "classifier_labels",
                                              {"data": info["manifest"].get("fingerprint")})
    if max_missed is not None:   # on the importance-sampled set: the refined one crowds the boundary
        classifier.calibrate(k_cls, healthy_cls, max_missed)
    timing["classifier_fit_s"] = time.perf_counter() - t0 - refine_info["assess_s"]
    timing["classifier_refine_assess_s"] = refine_info["assess_s"]
    verdict = None
    if bool(cfg.verdict_classifier):   # judges estimates: fitted on the training records' own, with eval.noise
        t0 = time.perf_counter()
        verdict = fit_verdict_classifier(_instantiate(cfg.classifier, "classifier"),
                                         lambda s, level: network(gappy(s)[0], level), samples_tr,
                                         rms(train.current), train.healthy, noise, seed + 11, max_missed)
        timing["verdict_classifier_fit_s"] = time.perf_counter() - t0

    store_cfg = info["metadata"].get("config") or {}
    nominal = (torch.tensor(common.actuator(DictConfig(store_cfg)).nominal_faults) if "actuator" in store_cfg
               else None)
    forward = fit_forward_check(pod, gappy, network, train.k, train.current, nominal, seed + 13) if cfg.forward_check else None
    metrics, arrays = evaluate_fdi(pod, gappy, network, val.current, val.k, noise, missing, seed, nominal)
    t0 = time.perf_counter()
    with torch.no_grad():
        network(gappy(samples_va)[0])
    timing["fdi_eval_per_signal_us"] = (time.perf_counter() - t0) / max(len(val), 1) * 1e6
    metrics.update(evaluate_classifier(classifier, val.k, val.healthy, arrays["k_hat"], verdict))
    metrics.update(measure_latency(gappy, network, classifier, samples_va, repeats))
    threshold, full_threshold = ood_thresholds(train.current, gappy, FullSignalCheck(pod.modes_, pod.mean_), noise,
                                               ood_q, seed + 7)
    with torch.no_grad():   # the shape statistics have physical thresholds: report how much of val they reject
        full_ood_val = float(FullSignalCheck(pod.modes_, pod.mean_, residual_threshold=full_threshold)(val.current)
                             .double().mean()) if len(val) else float("nan")
    metrics.update(
        n_train=len(train), n_fdi_fit=len(fit_rows), n_fdi_monitor=0 if monitor_rows is None else len(monitor_rows),
        n_val=len(val), n_modes=n_modes, n_points=n_points, n_hidden=n_hidden,
        n_layers=n_layers, n_members=n_members,
        selector=selector.name, selector_params=selector.get_params(), classifier=classifier.name,
        gappy_estimator=estimator, forward_check=forward.summary() if forward else None,
        model=module.optimizer_name + ("_e2e" if end_to_end else ""), fdi_inputs=fit["inputs"],
        classifier_threshold=float(classifier.threshold), n_classifier_train=len(k_all),
        classifier_refine=refine_info,
        energy_retained=float(pod.cumulative_energy()[n_modes - 1]), gappy_condition_number=gappy.condition_number(),
        ood_residual_threshold=threshold, ood_rate_val=float((arrays["residual"] > threshold).float().mean()),
        ood_full_residual_threshold=full_threshold, ood_full_rate_val=full_ood_val,
        eval_noise=noise, eval_missing=missing, best_epoch=keep.best_epoch, epochs_run=trainer.current_epoch,
        sample_rate=sample_rate, data_dir=str(cfg.data_dir), data_fingerprint=info["manifest"].get("fingerprint"),
        timing={k: round(v, 4) for k, v in timing.items()}, seed=seed,
        actuator=provenance.describe(prov["actuator"]), command=provenance.describe(prov["command"]))
    err = quartiles(arrays["err_alpha"])
    metrics.update(err_alpha_q1=err["q1"], err_alpha_q3=err["q3"])

    bundle = SurrogateBundle(pod, selector.indices_, network, classifier, sample_rate, threshold, ridge,
                             selector={"name": selector.name, "params": selector.get_params()},
                             meta={"data_fingerprint": info["manifest"].get("fingerprint"), "seed": seed,
                                   "model": metrics["model"], "n_train": len(train), "provenance": prov},
                             full_residual_threshold=full_threshold, gappy_statistics=statistics,
                             nominal_record=info["nominal"], verdict_classifier=verdict, forward_model=forward)
    bundle.save(out_dir / "surrogates.pt")
    with torch.no_grad():
        arrays.update(healthy=val.healthy, score=bundle.health_score(val.k), score_chain=bundle.verdict_score(arrays["k_hat"]),
                      indices=selector.indices_, time=grid, mode_1=pod.modes_[:, 0], energy=pod.energy_)
    _save_tensors(out_dir / "predictions.pt", arrays)
    common.write_json(out_dir / "metrics.json", metrics)
    return metrics, {"bundle": bundle, "pod": pod, "selector": selector, "module": module, "trainer": trainer,
                     "arrays": arrays, "out_dir": out_dir}


SUMMARY = ("err_alpha_median", "err_alpha_iqr", "err_k", "err_k_noise", "err_k_missing", "fdi_mae",
           "classifier_accuracy", "missed_fault_rate", "false_alarm_rate", "fdi_latency_us_p50")


@hydra.main(config_path=common.CONFIG_PATH, config_name="train", version_base="1.3")
@common.report_errors("phm-train")
def main(cfg: DictConfig) -> None:
    metrics, objects = train_surrogates(cfg)
    if metrics:
        log.info("wrote %s", objects["out_dir"] / "metrics.json")
        print(json.dumps({k: metrics[k] for k in SUMMARY}, indent=2), flush=True)


if __name__ == "__main__":
    main()
