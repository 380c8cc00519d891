"""``phm-generate``: the training data set of the surrogates, resumable and shardable.

Examples::

    phm-generate                                            # small quick set in data/quick
    phm-generate experiment=paper data_dir=/tmp/paper_data  # 10,000 / 500 / 100 (paper) + 40,000 labels
    phm-generate dataset.n_train=200 seed=3 data_dir=/tmp/d
    phm-generate -m hydra/launcher=joblib shard.count=2 'shard.index=range(2)'   # two processes
    phm-generate stage=merge                                # merge after independently run shards
    phm-generate dataset.life.n_actuators=40                # + run-to-failure histories in <data_dir>/life
    phm-generate stage=life dataset.life.n_actuators=40     # only those (no store needed)

Re-running a command resumes it; see docs/dataset.md. The work is the pipeline
:func:`phm_torch.pipelines.generate.generate` (its steps are listed there); :func:`generate` here composes its
settings from the config and calls it; :func:`main` is the thin Hydra entry point, printing the metrics.
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from functools import partial
from typing import Any

import hydra
from omegaconf import DictConfig

from ..assessment import AssessmentFunction
from ..pipelines import generate as pipeline
from ..pipelines.generate import GenerateSettings
from ..prognostics.damage import DamageModel
from . import common


def fingerprint(cfg: DictConfig) -> tuple[str, dict[str, Any]]:
    """SHA-256 of the data-defining nodes of a composed config (:func:`phm_torch.pipelines.generate.fingerprint`)
    and those nodes."""
    return pipeline.fingerprint(common.plain(cfg))


def settings_from_config(cfg: DictConfig) -> tuple[GenerateSettings, AssessmentFunction]:
    """The pipeline's settings and assessment function from a composed ``generate`` config (each value checked,
    errors naming its field)."""
    params = common.actuator(cfg)
    command = common.command(cfg.command)
    spec = common.build(cfg.dataset, "dataset")
    dev = common.device(cfg.device)
    assessment = common.build(cfg.assessment, "assessment", params=params, device=dev)
    settings = GenerateSettings(
        params=params,
        command=command,
        spec=spec,
        device=dev,
        seed=cfg.seed,
        data_dir=cfg.data_dir,
        stage=cfg.stage,
        shard_index=cfg.shard.index,
        shard_count=cfg.shard.count,
        overwrite=cfg.overwrite,
        repair=cfg.repair,
        progress=cfg.progress,
        provenance=common.requested_provenance(cfg),  # which actuator and command this store belongs to
        config=common.plain(cfg),
    )
    return settings, assessment


def generate(cfg: DictConfig) -> tuple[dict[str, Any], dict[str, Any]]:
    """Generate (or resume, or merge) the dataset store of ``cfg`` in ``cfg.data_dir``
    (:func:`phm_torch.pipelines.generate.generate`: its metrics and objects)."""
    settings, assessment = settings_from_config(cfg)
    common.set_threads(cfg)
    make_damage = None if cfg.get("damage") is None else partial(_damage, cfg.damage)
    return pipeline.generate(settings, assessment, make_damage)


def _damage(node: DictConfig, nominal: Sequence[float]) -> DamageModel:
    """The ``damage`` node's model for the nominal fault vector k_0 (8,) (built only when the life split runs)."""
    return common.build(node, "damage", nominal=nominal)


@hydra.main(config_path=common.CONFIG_PATH, config_name="generate", version_base="1.3")
@common.report_errors("phm-generate")
def main(cfg: DictConfig) -> None:
    metrics, _ = generate(cfg)
    print(json.dumps(metrics, indent=2), flush=True)


if __name__ == "__main__":
    main()
