"""``phm-generate``: the training data set of the surrogates, resumable and shardable.

Examples::

    phm-generate                                            # small quick set in data/quick
    phm-generate experiment=paper data_dir=/tmp/paper_data  # 10,000 / 500 / 100 (paper) + 40,000 labels
    phm-generate dataset.n_train=200 seed=3 data_dir=/tmp/d
    phm-generate -m hydra/launcher=joblib shard.count=2 'shard.index=range(2)'   # two processes
    phm-generate stage=merge                                # merge after independently run shards
    phm-generate dataset.life.n_actuators=40                # + run-to-failure histories in <data_dir>/life
    phm-generate stage=life dataset.life.n_actuators=40     # only those (no store needed)

Re-running a command resumes it; see docs/dataset.md. The work is done by :func:`generate` (a plain
function of the composed config); :func:`main` is the thin Hydra entry point.
"""

from __future__ import annotations

import hashlib
import json
import logging
import subprocess
import time
from pathlib import Path
from typing import Any

import hydra
import torch
from omegaconf import DictConfig

from .. import __version__, provenance
from ..assessment import AssessmentFunction
from ..command import time_grid
from ..data import calibration, life_files
from ..data import generation as gen
from ..data import life as life_split
from ..data.labels import LabelComputer, make_label_plan
from ..data.store import read_json
from ..params import CONF_DIR
from . import common

log = logging.getLogger(__name__)

# Config nodes that determine the data (the fingerprint); the rest only says where and how to run.
DATA_NODES = ("actuator", "command", "dataset", "assessment", "seed")
# dataset.life is not in it: a life split is added to a finished store without invalidating it; the life
# data record their own settings (truth.json) and resume per actuator on their own key.
NOT_FINGERPRINTED = ("life",)
STAGES = (*gen.STAGES, "life")  # life: only the life split (no store)


def git_revision() -> str:
    """The repository's HEAD commit (with ``-dirty`` if modified), or ``unknown``."""
    root = CONF_DIR.parent
    try:
        rev = subprocess.run(
            ["git", "rev-parse", "HEAD"], cwd=root, capture_output=True, text=True, timeout=10, check=True
        ).stdout.strip()
        dirty = subprocess.run(
            ["git", "status", "--porcelain", "--untracked-files=no"],
            cwd=root,
            capture_output=True,
            text=True,
            timeout=10,
            check=True,
        ).stdout.strip()
    except (OSError, subprocess.SubprocessError):
        return "unknown"
    return rev + ("-dirty" if dirty else "")


def fingerprint(cfg: DictConfig) -> tuple[str, dict[str, Any]]:
    """SHA-256 of the data-defining config (canonical JSON) and that config."""
    data = {key: common.plain(cfg.get(key)) for key in DATA_NODES}
    if isinstance(data["dataset"], dict):
        data["dataset"] = {k: v for k, v in data["dataset"].items() if k not in NOT_FINGERPRINTED}
    data["package_version"] = __version__
    text = json.dumps(data, sort_keys=True, separators=(",", ":"))
    return hashlib.sha256(text.encode()).hexdigest(), data


def generate(cfg: DictConfig) -> tuple[dict[str, Any], dict[str, Any]]:
    """Generate (or resume, or merge) the dataset store of ``cfg`` in ``cfg.data_dir``.

    Returns:
        ``metrics``: per split count and healthy count, wall time, throughput of this run (signals/s,
        assessment ms/vector over every vector assessed, labels/s of the labels split, all including the
        one-off compilations), signal chunks computed/reused/repaired (``chunks``) and the same for the
        labels chunks (``label_chunks``, when ``dataset.n_labels`` > 0), whether the store is complete;
        ``objects``: ``data_dir`` (Path), ``manifest`` (dict or None), ``plan``, ``label_plan`` (or None).
    """
    params = common.actuator(cfg)
    command = common.command(cfg.command)
    duration = common.number(getattr(command, "duration", None), "command.duration", 0.0, strict=True)
    spec: gen.DatasetSpec = common.build(cfg.dataset, "dataset")
    dev = common.device(cfg.device)
    assessment: AssessmentFunction = common.build(cfg.assessment, "assessment", params=params, device=dev)
    seed = common.integer(cfg.seed, "seed", 0)
    prov = common.requested_provenance(cfg)  # which actuator and command this store belongs to
    count = common.integer(cfg.shard.count, "shard.count", 1)
    index = common.integer(cfg.shard.index, "shard.index", 0)
    if index >= count:
        raise ValueError(f"shard.index must be in [0, shard.count - 1] = [0, {count - 1}], got {index}")
    stage = cfg.stage
    if stage not in STAGES:
        raise ValueError(f"stage must be one of {list(STAGES)}, got {stage!r}")
    common.set_threads(cfg)
    if not isinstance(cfg.data_dir, str) or not cfg.data_dir.strip():
        raise ValueError(f"data_dir must be a directory path, got {cfg.data_dir!r}")
    data_dir = Path(cfg.data_dir).expanduser().resolve()
    if stage == "life":
        if spec.life.n_actuators == 0:
            raise ValueError("stage=life needs dataset.life.n_actuators > 0, got 0")
        gen.check_writable(data_dir)
        life = _life(cfg, spec, params, command, duration, assessment, seed, prov, dev, data_dir)
        return {"data_dir": str(data_dir), "stage": stage, "life": life}, {"data_dir": data_dir}

    fp, data_cfg = fingerprint(cfg)
    gen.prepare_store(data_dir, fp, data_cfg, bool(cfg.overwrite))
    # the importance sampler calibrated to dataset.healthy_fraction (a pilot, cached in data_dir)
    sampling, pilot_s = calibration.load_or_calibrate(
        data_dir, fp, lambda: calibration.calibrate_spec(spec, params.nominal_faults, assessment, seed)
    )
    q = float(sampling["distance_exponent"])
    plan = gen.make_plan(spec, params.nominal_faults, seed, q)
    label_plan = make_label_plan(spec, params.nominal_faults, seed, q)
    plans = [p for p in (plan, label_plan) if p is not None]
    t0 = time.perf_counter()
    counts = {"computed": 0, "reused": 0, "repaired": 0}
    label_counts = dict(counts)
    computer: gen.ChunkComputer | None = None
    labeller: LabelComputer | None = None
    if gen.is_complete(data_dir, fp) and stage != "merge":
        log.info("%s already holds the finished store of this config", data_dir)
    else:
        if stage in ("all", "chunks"):

            def compute(k, effect_values=None):
                nonlocal computer
                if computer is None:
                    computer = gen.ChunkComputer(params, command, duration, spec, assessment, dev)
                return computer(k, effect_values)

            repair, progress = bool(cfg.repair), bool(cfg.progress)
            counts = gen.compute_chunks(data_dir, plan, fp, compute, index, count, repair, progress)
            if label_plan is not None:
                labeller = LabelComputer(assessment, params.nominal_faults, label_plan.chunk_size)
                label_counts = gen.compute_chunks(data_dir, label_plan, fp, labeller, index, count, repair, progress)
        missing = {p.layout.unit: m for p in plans if (m := gen.missing_chunks(data_dir, p))}
        if stage == "merge" or (stage == "all" and not missing):
            grid = time_grid(duration, params.sample_rate)
            seeds = {"seed": seed, **plan.seeds, **(label_plan.seeds if label_plan is not None else {})}
            metadata = {
                "config": common.plain(cfg),
                "fingerprint": fp,
                "seeds": seeds,
                "provenance": prov,
                "package_version": __version__,
                "git_revision": git_revision(),
                "torch_version": torch.__version__,
                "margin_names": list(gen.MARGIN_NAMES),
                "sampling": sampling,
                "assessment_sweep": assessment.record(),
            }
            extra = {
                "seed": seed,
                "provenance": prov,
                "package_version": __version__,
                "chunk_size": plan.chunk_size,
                "n_chunks": plan.n_chunks,
                "sampling": sampling,
                "assessment_sweep": assessment.record(),
            }
            if label_plan is not None:
                extra |= {"label_chunk_size": label_plan.chunk_size, "n_label_chunks": label_plan.n_chunks}
            gen.merge(data_dir, plan, fp, grid.numpy(), command(grid).numpy(), metadata, extra, labels=label_plan)
        elif missing:
            log.info(
                "chunks %s are not done yet (other shards); run with stage=merge once they are",
                "; ".join(f"{unit} {m}" for unit, m in missing.items()),
            )
    wall = time.perf_counter() - t0

    complete = gen.is_complete(data_dir, fp)
    life = None
    if spec.life.n_actuators > 0 and stage != "chunks" and index == 0:  # one shard writes it
        life = _life(cfg, spec, params, command, duration, assessment, seed, prov, dev, data_dir)
    manifest = read_json(data_dir / gen.MANIFEST_FILE) if complete else None
    metrics: dict[str, Any] = {
        "data_dir": str(data_dir),
        "complete": complete,
        "fingerprint": fp,
        "actuator": provenance.describe(prov["actuator"]),
        "command": provenance.describe(prov["command"]),
        "shard": {"index": index, "count": count},
        "stage": stage,
        "chunks": {"total": plan.n_chunks, **counts},
    }
    if label_plan is not None:
        metrics["label_chunks"] = {"total": label_plan.n_chunks, **label_counts}
    metrics["wall_time_s"] = round(wall, 2)
    metrics["sampling"] = {**sampling, "pilot_s": round(pilot_s, 2)}
    metrics["assessment_sweep"] = {
        "frequencies": list(assessment.sweep.frequencies),
        "amplitude": assessment.sweep.amplitude,
        "auto": assessment.auto,
    }
    if manifest is not None:
        metrics["splits"] = {
            s: {
                "count": v["count"],
                "healthy": v["healthy"],
                "healthy_fraction": round(v["healthy"] / v["count"], 4) if v["count"] else None,
                "unmeasurable": v.get("unmeasurable"),
            }
            for s, v in manifest["splits"].items()
        }
    timing: dict[str, float] = {}
    if computer is not None:
        n_sig = counts["computed"] * spec.chunk_size
        metrics["signals_per_s"] = round(n_sig / max(computer.timing["signals_s"], 1e-9), 2)
        timing |= computer.timing
    if labeller is not None and labeller.vectors:  # vectors assessed for the labels split, padding included
        metrics["labels_per_s"] = round(labeller.vectors / max(labeller.timing["labels_s"], 1e-9), 2)
        timing |= labeller.timing
    if pilot_s:
        timing["pilot_s"] = pilot_s
    if life is not None:
        metrics["life"] = life
    if timing and assessment.vectors:
        metrics["assessment_ms_per_vector"] = round(1000 * assessment.wall_s / assessment.vectors, 3)
        metrics["timing_s"] = {k: round(v, 2) for k, v in timing.items()}
    return metrics, {"data_dir": data_dir, "manifest": manifest, "plan": plan, "label_plan": label_plan}


def _life(
    cfg: DictConfig,
    spec: gen.DatasetSpec,
    params: Any,
    command: Any,
    duration: float,
    assessment: Any,
    seed: int,
    prov: dict[str, Any],
    dev: torch.device,
    data_dir: Path,
) -> dict[str, Any]:
    """Write (or resume) the life split of ``cfg`` into ``<data_dir>/life``; returns its metrics."""
    if cfg.get("damage") is None:
        raise ValueError("damage: the life split needs a damage model (damage=coupled)")
    damage = common.build(cfg.damage, "damage", nominal=list(params.nominal_faults))
    life = spec.life
    simulate = life_split.simulator(
        params, spec.fidelity, spec.substeps, spec.effects, life.compile, command, duration, dev
    )
    generator = life_split.LifeGenerator(
        life,
        damage,
        lambda k: assessment(k).healthy,
        simulate,
        gen.seed_streams(seed)["life"],
        params.nominal_faults,
        spec.uniform,
        spec.label_chunk_size,
    )
    signal = {"fidelity": spec.fidelity, "substeps": spec.substeps, "effects": common.plain(spec.effects)}
    settings = life_split.settings_record(life)
    key_data = {
        "life": {k: v for k, v in settings.items() if k not in ("n_actuators", "batch", "compile")},
        "seed": seed,
        "actuator": prov["actuator"],
        "command": prov["command"],
        "damage": common.plain(cfg.damage),
        "assessment": common.plain(cfg.assessment),
        "signal": signal,
    }
    header = {
        "actuator": prov["actuator"],
        "command": prov["command"],
        "damage": common.plain(cfg.damage),
        "every_hours": float(life.every),
        "life": settings,
        "seed": seed,
        "signal": signal,
        "assessment": common.plain(cfg.assessment),
        "package_version": __version__,
    }
    return life_files.generate_life(
        data_dir / life_files.LIFE_DIR, generator, key_data, header, bool(cfg.overwrite), bool(cfg.progress)
    )


@hydra.main(config_path=common.CONFIG_PATH, config_name="generate", version_base="1.3")
@common.report_errors("phm-generate")
def main(cfg: DictConfig) -> None:
    metrics, _ = generate(cfg)
    print(json.dumps(metrics, indent=2), flush=True)


if __name__ == "__main__":
    main()
