"""``phm-evaluate``: RUL on the ``rul`` split from the true k and from the full online flow, against the
physics reference; writes metrics.json, the figures, rul_calibration.json and the exported pipeline.

The work is the pipeline :func:`phm_torch.pipelines.evaluate.evaluate_rul`; :func:`evaluate_rul` here composes
its settings from the config, calls it and writes what it returns (``rul_calibration.json``,
``rul_predictions.json``, the exported files of ``export_formats``, ``metrics.json``); :func:`main` is the thin
Hydra entry point.
"""

from __future__ import annotations

import json
import logging
from pathlib import Path
from typing import Any

import hydra
from omegaconf import DictConfig

from .. import provenance
from ..online.formats import check_formats, write_checked
from ..pipelines import evaluate as pipeline
from ..pipelines.evaluate import CalibrationSettings, EvaluateSettings, ReferenceSettings, RULSettings
from . import common

log = logging.getLogger(__name__)


def settings_from_config(cfg: DictConfig) -> EvaluateSettings:
    """The pipeline's settings from a composed ``evaluate`` config (each value checked, errors naming its field)."""
    rul, reference = cfg.rul, cfg.reference
    return EvaluateSettings(
        data_dir=str(cfg.data_dir),
        split=str(cfg.split),
        bundle=str(cfg.bundle),
        out_dir=Path(str(cfg.out_dir)),
        seed=cfg.seed,
        damage=common.plain(cfg.damage),
        assessment=common.plain(cfg.assessment) if cfg.get("assessment") is not None else None,
        rul=RULSettings(rul.n_samples, rul.refine_iterations, rul.delta_bracket, rul.band),
        reference=ReferenceSettings(reference.step_hours, reference.refine_iterations),
        calibration=CalibrationSettings.from_nodes(
            common.plain(cfg.fdi_band),
            common.plain(cfg.verdict),
            common.plain(cfg.fdi_interval),
            cfg.consistency.quantile,
            cfg.ood.quantile,
        ),
        min_present=cfg.online.min_present,
        requested_provenance=common.requested_provenance(cfg),
        explicit=frozenset(k for k in provenance.KEYS if cfg.get(k) is not None),
        fallback_actuator=common.actuator(cfg) if cfg.get("actuator") is not None else None,
    )


def evaluate_rul(cfg: DictConfig) -> tuple[dict[str, Any], dict[str, Any]]:
    """Evaluate and calibrate (:func:`phm_torch.pipelines.evaluate.evaluate_rul`), then write its outputs under
    ``out_dir``; returns its ``(metrics, objects)``, metrics with the export's figures."""
    common.set_threads(cfg)
    formats = check_formats(common.plain(cfg.export_formats)) if cfg.export else []
    settings = settings_from_config(cfg)
    metrics, objects = pipeline.evaluate_rul(settings)
    out_dir = settings.out_dir
    common.write_json(out_dir / "rul_calibration.json", objects["calibration"])
    common.write_json(out_dir / "rul_predictions.json", objects["predictions"])
    if cfg.export:  # each format of export_formats beside online.pt, reloaded and compared with eager
        checked = write_checked(
            objects["pipeline"], out_dir / "online.pt", formats, objects["export_metadata"], objects["probe"]
        )
        metrics["export_max_abs_diff"] = max(checked["max_abs_diff"].values())
        metrics["export"] = next(iter(checked["files"].values()))
        metrics["export_files"], metrics["export_max_abs_diff_by_format"] = checked["files"], checked["max_abs_diff"]
    common.write_json(out_dir / "metrics.json", metrics)
    return metrics, objects


@hydra.main(config_path=common.CONFIG_PATH, config_name="evaluate", version_base="1.3")
@common.report_errors("phm-evaluate")
def main(cfg: DictConfig) -> None:
    metrics, _ = evaluate_rul(cfg)
    print(json.dumps(metrics, indent=2), flush=True)


if __name__ == "__main__":
    main()
