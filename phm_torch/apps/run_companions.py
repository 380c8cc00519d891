"""phm-run's ``companions`` stage: the tracker's two companion files of the evaluate stage's pipeline.

phm-track reads, beside a pipeline, its FDI response (``<stem>.fdi_response.json``: the pipeline's mean k_hat
against the truth near nominal, inverted before fusing) and a near-nominal FDI (``<stem>.near_nominal.pt``: a
network trained where an actuator spends its life, read instead of the pipeline's k_hat there); without them the
tracker reads the pipeline's k_hat as it is (docs/prognostics.md, "Life tracking"). Both are learned from
run-to-failure histories with their truth, which must not be the histories the track stage scores, so this stage
generates a life split of its own (the generate stage's settings and seed + 1, ``companions.life_actuators``
histories), tracks it with the truth to fit the response, and trains and calibrates the near-nominal FDI on it and
on the store's near-nominal records (:func:`~phm_torch.tracking.near_nominal_training.train_near_nominal`).
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any

import torch
from omegaconf import DictConfig

from ..tracking.companions import SUFFIXES
from ..tracking.near_nominal_training import NearNominalTraining, train_near_nominal
from ..tracking.response import RESPONSE_BINS, RESPONSE_MIN_COUNT, FDIResponse
from . import common, schema
from .stage_config import compose_stage

log = logging.getLogger(__name__)
VERDICT_MODES = ("record", "posterior")  # TrackerSettings.verdict; the first is the default
OWN_KEYS = ("data_dir", "stage", "seed", "dataset.life.n_actuators")  # set by this stage for its life split
# the near-nominal training's code defaults under companions.near_nominal (conf/run.yaml composes them in first)
schema.register("run_companions", {"near_nominal": schema.node(NearNominalTraining())})


def choose_verdict(tracked: dict[str, dict[str, Any]]) -> dict[str, Any]:
    """The tracker's verdict mode for a pipeline from its tracks of one life split in each mode (phm-track's
    metrics, with the truth): the mode that flagged more ends of life within one inspection, ``record`` (the
    tracker's default) on a tie. A pipeline whose own verdict raises false alarms near nominal (a small training set,
    importance-sampled far from nominal) flags most ends of life far too early with ``record``."""
    figures = {
        key: {mode: (m.get("tracker") or {}).get(key) for mode, m in tracked.items()}
        for key in ("eol_flagged_within_one_inspection", "eol_flagged_early", "prognostic_horizon", "alpha_lambda")
    }
    within = {mode: v if v is not None else -1.0 for mode, v in figures["eol_flagged_within_one_inspection"].items()}
    best = max(within.values())
    chosen = "record" if within.get("record") == best else max(within, key=within.__getitem__)
    return {"verdict": chosen, **figures}


def companion_paths(pipeline: Path) -> dict[str, Path]:
    """{kind: the path phm-track's ``auto`` reads for it} beside ``pipeline``."""
    return {kind: pipeline.with_name(pipeline.stem + suffix) for kind, suffix in SUFFIXES.items()}


def remove_stale(pipeline: Path) -> list[str]:
    """Delete companion files beside ``pipeline`` (they belong to the pipeline it replaces); the removed paths."""
    removed = []
    for path in companion_paths(pipeline).values():
        if path.is_file():
            path.unlink()
            removed.append(str(path))
    return removed


def run_companions(
    cfg: DictConfig,
    run_dir: Path,
    data_dir: Path,
    pipeline: Path,
    shared: list[str],
    damage: list[str],
    generate_overrides: list[str],
) -> dict[str, Any]:
    """Make both companion files of ``pipeline`` (see the module docstring); returns the stage's metrics.

    ``shared`` / ``damage`` / ``generate_overrides``: the run's overrides of the actuator and command, of the damage
    law and of its generate stage (:mod:`.stage_config`)."""
    from .generate import generate
    from .track import track

    node = common.plain(cfg.companions)
    if not isinstance(node, dict):
        raise ValueError(f"companions must be a mapping, got {node!r}")
    n_actuators = common.integer(node.get("life_actuators"), "companions.life_actuators", 5)
    threads = common.integer(node.get("threads", 1), "companions.threads", 1)
    settings = common.build(cfg.companions.near_nominal, "companions.near_nominal")
    if not pipeline.is_file():
        raise ValueError(f"stages: companions needs the evaluate stage's pipeline ({pipeline} does not exist)")
    kept = [o for o in generate_overrides if o.split("=", 1)[0].lstrip("+~") not in OWN_KEYS]
    seed = int(compose_stage("generate", [*shared, *damage, *kept]).seed) + 1  # not the track stage's histories
    root = run_dir / "companions"
    life_dir = root / "data"
    gen_metrics, _ = generate(
        compose_stage(
            "generate",
            [
                *shared,
                *damage,
                *kept,
                f"data_dir={life_dir}",
                "stage=life",
                f"seed={seed}",
                f"dataset.life.n_actuators={n_actuators}",
            ],
        )
    )
    paths = companion_paths(pipeline)
    remove_stale(pipeline)
    life = life_dir / "life"
    # the pipeline's own k_hat (no companions) tracked against the truth of this split, once with each verdict mode:
    # the first fits the response; the pair chooses the tracker's verdict mode for this pipeline (verdict=auto)
    n_rows = len((life / "index.csv").read_text().strip().splitlines()) - 1
    fit = n_rows >= RESPONSE_BINS * RESPONSE_MIN_COUNT
    if not fit:
        log.warning(
            "companions: %d inspections are too few to fit the FDI response (%d needed): none written; the tracker "
            "reads the pipeline's k_hat without it (companions.life_actuators=%d: give more histories)",
            n_rows,
            RESPONSE_BINS * RESPONSE_MIN_COUNT,
            n_actuators,
        )
    tracked = {}
    for mode in VERDICT_MODES:
        tracked[mode], _ = track(
            compose_stage(
                "track",
                [
                    *shared,
                    *damage,
                    f"index={life / 'index.csv'}",
                    f"pipeline={pipeline}",
                    f"truth={life / 'truth.json'}",
                    f"out_dir={root / f'track_{mode}'}",
                    "response=null",
                    "near_nominal=null",
                    f"verdict={mode}",
                    *([f"response_out={paths['response']}"] if fit and mode == VERDICT_MODES[0] else []),
                ],
            )
        )
    verdict = choose_verdict(tracked)
    previous = torch.get_num_threads()
    torch.set_num_threads(threads)
    try:
        store = data_dir if (data_dir / "dataset.h5").is_file() else None
        net, report = train_near_nominal(pipeline, life, settings, store)
    except ValueError as err:  # too few histories to train on or to calibrate with: say which setting gives more
        raise ValueError(
            f"companions: {err} (companions.life_actuators={n_actuators}: give more histories, or "
            "companions.near_nominal.holdout / gate to calibrate on more of them)"
        ) from err
    finally:
        torch.set_num_threads(previous)
    net.provenance["tracker_verdict"] = verdict
    net.save(paths["near_nominal"])
    log.info("companions of %s: %s", pipeline, ", ".join(str(p) for p in paths.values() if p.is_file()))
    response = FDIResponse.load(paths["response"]) if fit else None
    return {
        "life_actuators": n_actuators,
        "life_seed": seed,
        "life_inspections": tracked[VERDICT_MODES[0]]["inspections"],
        "tracker_verdict": verdict,
        "life_generate": gen_metrics.get("life"),
        "response": None if response is None else str(paths["response"]),
        "response_corrected": None if response is None else response.corrected,
        "near_nominal": str(paths["near_nominal"]),
        "near_nominal_settings": {k: common.plain(v) for k, v in vars(settings).items()},
        "near_nominal_records": {"life": report["life_records"], "store": report["store_records"]},
        "near_nominal_heldout_rms": report["heldout"],
    }
