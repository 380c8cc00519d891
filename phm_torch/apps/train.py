"""``phm-train``: learn the surrogates from a dataset store; write metrics.json and the SurrogateBundle.

Examples::

    phm-train                                                   # store data/quick, the paper's choices
    phm-train data_dir=data/paper out_dir=results/paper
    phm-train model=fdi_e2e selector=greedy n_points=40
    phm-train -m experiment=ablation_hidden data_dir=data/paper # Hydra multirun sweep

The work is the pipeline :func:`phm_torch.pipelines.train.train_surrogates` (its steps are listed there);
:func:`train_surrogates` here composes its settings from the config, calls it and writes what it returns
(``surrogates.pt``, ``predictions.pt``, ``metrics.json``); :func:`main` is the thin Hydra entry point.
"""

from __future__ import annotations

import json
import logging
from functools import partial
from pathlib import Path
from typing import Any

import hydra
import torch
from hydra.errors import InstantiationException
from hydra.utils import instantiate
from omegaconf import DictConfig

from .. import provenance
from ..io.atomic import atomic_open
from ..pipelines import train as pipeline
from ..pipelines.train import EvalSettings, GappySettings, TrainSettings
from ..surrogates.classifiers.refinement import BoundaryRefinement
from . import common

log = logging.getLogger(__name__)

SUMMARY = (
    "err_alpha_median",
    "err_alpha_iqr",
    "err_k",
    "err_k_noise",
    "err_k_missing",
    "fdi_mae",
    "classifier_accuracy",
    "missed_fault_rate",
    "false_alarm_rate",
    "fdi_latency_us_p50",
)


def _instantiate(node: Any, name: str, **kwargs: Any) -> Any:
    """Instantiate a config node; a constructor error is reported as ``name: ...``."""
    try:
        return instantiate(node, **kwargs)
    except InstantiationException as e:
        cause = e.__cause__ if e.__cause__ is not None else e
        raise ValueError(f"{name}: {cause}") from None


def _out_dir(cfg: DictConfig) -> Path:
    """``out_dir``, except in a Hydra multirun, where every job writes into its own sweep subdirectory."""
    from hydra.core.hydra_config import HydraConfig
    from hydra.types import RunMode

    if HydraConfig.initialized() and HydraConfig.get().mode == RunMode.MULTIRUN:
        return Path(HydraConfig.get().runtime.output_dir)
    return Path(str(cfg.out_dir)).expanduser()


def settings_from_config(cfg: DictConfig) -> TrainSettings:
    """The pipeline's settings from a composed ``train`` config (each value checked, errors naming its field)."""
    model = _instantiate(cfg.model, "model", _convert_="all")
    refine = cfg.classifier_refine
    return TrainSettings(
        data_dir=str(cfg.data_dir),
        out_dir=_out_dir(cfg),
        splits={k: str(v) for k, v in common.plain(cfg.splits).items()},
        limits=common.plain(cfg.limit) or {},
        seed=cfg.seed,
        n_modes=cfg.n_modes,
        n_points=cfg.n_points,
        n_hidden=cfg.n_hidden,
        n_layers=cfg.n_layers,
        n_members=cfg.n_members,
        model=model,
        pod_solver=str(cfg.pod.solver),
        gappy=GappySettings(str(cfg.gappy.estimator), cfg.gappy.ridge),
        eval=EvalSettings(cfg.eval.noise, cfg.eval.missing, cfg.eval.ood_quantile, cfg.eval.latency_repeats),
        monitor_fraction=cfg.monitor_fraction,
        max_missed_fault_rate=cfg.calibration.max_missed_fault_rate,
        verdict_max_missed_fault_rate=cfg.calibration.get("verdict_max_missed_fault_rate"),
        classifier_labels=bool(cfg.classifier_labels),
        refine=BoundaryRefinement(
            refine.rounds, refine.labels_per_round, refine.candidates_per_label, refine.path_labels_per_round
        ),
        refine_device=str(refine.device),
        verdict_classifier=bool(cfg.verdict_classifier),
        forward_check=bool(cfg.forward_check),
        loggers=common.plain(cfg.loggers) or [],
        trainer=common.plain(cfg.trainer),
        ckpt_path=None if cfg.ckpt_path is None else str(cfg.ckpt_path),
        requested_provenance=common.requested_provenance(cfg),
        explicit_provenance=frozenset(k for k in provenance.KEYS if cfg.get(k) is not None),
        drive_range=cfg.drive_range,
        fit_within_drive_range=bool(cfg.fit_within_drive_range),
        damage=common.plain(cfg.damage) if cfg.get("damage") is not None else None,
    )


def train_surrogates(cfg: DictConfig) -> tuple[dict[str, Any], dict[str, Any]]:
    """Train every surrogate from the store ``cfg.data_dir`` and evaluate it on the validation split
    (:func:`phm_torch.pipelines.train.train_surrogates`).

    Returns:
        ``metrics`` (also written to ``out_dir/metrics.json``; errors and rates are fractions) and
        ``objects``: ``bundle`` (:class:`SurrogateBundle`, saved as ``out_dir/surrogates.pt``), ``pod``,
        ``selector``, ``module`` (the FDIModule), ``trainer``, ``arrays`` (validation predictions, saved
        as ``out_dir/predictions.pt``), ``out_dir``.
    """
    common.set_threads(cfg)
    settings = settings_from_config(cfg)
    selector = _instantiate(cfg.selector, "selector")
    make_classifier = partial(_instantiate, cfg.classifier, "classifier")
    metrics, objects = pipeline.train_surrogates(settings, selector, make_classifier)
    if metrics:  # rank zero of a multi-device run writes
        out_dir = objects["out_dir"]
        objects["bundle"].save(out_dir / "surrogates.pt")
        with atomic_open(out_dir / "predictions.pt", "wb") as fh:
            torch.save({k: v.detach().cpu() for k, v in objects["arrays"].items()}, fh)
        common.write_json(out_dir / "metrics.json", metrics)
    return metrics, objects


@hydra.main(config_path=common.CONFIG_PATH, config_name="train", version_base="1.3")
@common.report_errors("phm-train")
def main(cfg: DictConfig) -> None:
    metrics, objects = train_surrogates(cfg)
    if metrics:
        log.info("wrote %s", objects["out_dir"] / "metrics.json")
        print(json.dumps({k: metrics[k] for k in SUMMARY}, indent=2), flush=True)


if __name__ == "__main__":
    main()
