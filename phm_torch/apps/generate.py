"""``phm-generate``: the training data set of the surrogates, resumable and shardable.

Examples::

    phm-generate                                            # small quick set in data/quick
    phm-generate experiment=paper data_dir=/tmp/paper_data  # 10,000 / 500 / 100 (paper)
    phm-generate dataset.n_train=200 seed=3 data_dir=/tmp/d
    phm-generate -m hydra/launcher=joblib shard.count=2 'shard.index=range(2)'   # two processes
    phm-generate stage=merge                                # merge after independently run shards

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

from .. import __version__
from ..assessment import AssessmentFunction
from ..command import time_grid
from ..data import generation as gen
from ..data.store import DatasetStore, read_json
from ..params import CONF_DIR
from . import common

log = logging.getLogger(__name__)

# Config nodes that determine the data (the fingerprint); the rest only says where and how to run.
DATA_NODES = ("actuator", "command", "dataset", "assessment", "seed")


def git_revision() -> str:
    """The repository's HEAD commit (with ``-dirty`` if modified), or ``unknown``."""
    root = CONF_DIR.parent
    try:
        rev = subprocess.run(["git", "rev-parse", "HEAD"], cwd=root, capture_output=True, text=True,
                             timeout=10, check=True).stdout.strip()
        dirty = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no"], cwd=root,
                               capture_output=True, text=True, timeout=10, check=True).stdout.strip()
    except (OSError, subprocess.SubprocessError):
        return "unknown"
    return rev + ("-dirty" if dirty else "")


def fingerprint(cfg: DictConfig) -> tuple[str, dict[str, Any]]:
    """SHA-256 of the data-defining config (canonical JSON) and that config."""
    data = {key: common.plain(cfg.get(key)) for key in DATA_NODES}
    data["package_version"] = __version__
    text = json.dumps(data, sort_keys=True, separators=(",", ":"))
    return hashlib.sha256(text.encode()).hexdigest(), data


def generate(cfg: DictConfig) -> tuple[dict[str, Any], dict[str, Any]]:
    """Generate (or resume, or merge) the dataset store of ``cfg`` in ``cfg.data_dir``.

    Returns:
        ``metrics``: per split count and healthy count, wall time, throughput of this run (signals/s,
        assessment ms/vector, both including the one-off compilations), chunks computed/reused/repaired,
        whether the store is complete;
        ``objects``: ``data_dir`` (Path), ``manifest`` (dict or None), ``plan``.
    """
    params = common.actuator(cfg)
    command = common.command(cfg.command)
    duration = common.number(getattr(command, "duration", None), "command.duration", 0.0, strict=True)
    spec: gen.DatasetSpec = common.build(cfg.dataset, "dataset")
    dev = common.device(cfg.get("device", "cpu"))
    assessment: AssessmentFunction = common.build(cfg.assessment, "assessment", params=params, device=dev)
    seed = common.integer(cfg.seed, "seed", 0)
    count = common.integer(cfg.shard.count, "shard.count", 1)
    index = common.integer(cfg.shard.index, "shard.index", 0)
    if index >= count:
        raise ValueError(f"shard.index must be in [0, shard.count - 1] = [0, {count - 1}], got {index}")
    stage = cfg.get("stage", "all")
    if stage not in gen.STAGES:
        raise ValueError(f"stage must be one of {list(gen.STAGES)}, got {stage!r}")
    threads = cfg.get("threads")
    if threads is not None:
        torch.set_num_threads(common.integer(threads, "threads", 1))
    if not isinstance(cfg.data_dir, str) or not cfg.data_dir.strip():
        raise ValueError(f"data_dir must be a directory path, got {cfg.data_dir!r}")
    data_dir = Path(cfg.data_dir).expanduser().resolve()

    fp, data_cfg = fingerprint(cfg)
    gen.prepare_store(data_dir, fp, data_cfg, bool(cfg.get("overwrite", False)))
    plan = gen.make_plan(spec, params.nominal_faults, seed)
    t0 = time.perf_counter()
    counts = {"computed": 0, "reused": 0, "repaired": 0}
    computer: gen.ChunkComputer | None = None
    if gen.is_complete(data_dir, fp) and stage != "merge":
        log.info("%s already holds the finished store of this config", data_dir)
    else:
        if stage in ("all", "chunks"):
            def compute(k):
                nonlocal computer
                if computer is None:
                    computer = gen.ChunkComputer(params, command, duration, spec, assessment, dev)
                return computer(k)

            counts = gen.compute_chunks(data_dir, plan, fp, compute, index, count, bool(cfg.get("repair", False)),
                                        bool(cfg.get("progress", True)))
        missing = gen.missing_chunks(data_dir, plan)
        if stage == "merge" or (stage == "all" and not missing):
            grid = time_grid(duration, params.sample_rate)
            metadata = {"config": common.plain(cfg), "fingerprint": fp, "seeds": {"seed": seed, **plan.seeds},
                        "package_version": __version__, "git_revision": git_revision(),
                        "torch_version": torch.__version__, "margin_names": list(gen.MARGIN_NAMES)}
            gen.merge(data_dir, plan, fp, grid.numpy(), command(grid).numpy(), metadata,
                      {"seed": seed, "package_version": __version__, "chunk_size": plan.chunk_size,
                       "n_chunks": plan.n_chunks})
        elif missing:
            log.info("chunks %s are not done yet (other shards); run with stage=merge once they are", missing)
    wall = time.perf_counter() - t0

    complete = gen.is_complete(data_dir, fp)
    manifest = read_json(data_dir / gen.MANIFEST_FILE) if complete else None
    metrics: dict[str, Any] = {"data_dir": str(data_dir), "complete": complete, "fingerprint": fp,
                               "shard": {"index": index, "count": count}, "stage": stage,
                               "chunks": {"total": plan.n_chunks, **counts}, "wall_time_s": round(wall, 2)}
    if manifest is not None:
        metrics["splits"] = {s: {"count": v["count"], "healthy": v["healthy"],
                                 "healthy_fraction": round(v["healthy"] / v["count"], 4) if v["count"] else None}
                             for s, v in manifest["splits"].items()}
    if computer is not None and assessment.vectors:
        n_sig = counts["computed"] * spec.chunk_size
        metrics["signals_per_s"] = round(n_sig / max(computer.timing["signals_s"], 1e-9), 2)
        metrics["assessment_ms_per_vector"] = round(1000 * assessment.wall_s / assessment.vectors, 3)
        metrics["timing_s"] = {k: round(v, 2) for k, v in computer.timing.items()}
    return metrics, {"data_dir": data_dir, "manifest": manifest, "plan": plan}


def open_store(data_dir: str | Path, verify: bool = False) -> DatasetStore:
    """Open a finished store for reading (lazy)."""
    return DatasetStore(data_dir, verify=verify)


@hydra.main(config_path=common.CONFIG_PATH, config_name="generate", version_base="1.3")
@common.report_errors("phm-generate")
def main(cfg: DictConfig) -> None:
    metrics, _ = generate(cfg)
    print(json.dumps(metrics, indent=2), flush=True)


if __name__ == "__main__":
    main()
