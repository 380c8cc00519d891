"""phm-run's ``companions`` stage: the tracker's two companion files of the evaluate stage's pipeline.

phm-track reads, beside a pipeline, its FDI response (``<stem>.fdi_response.json``: the pipeline's mean k_hat
against the truth near nominal, inverted before fusing) and a near-nominal FDI (``<stem>.near_nominal.pt``: a
network trained where an actuator spends its life, read instead of the pipeline's k_hat there); without them the
tracker reads the pipeline's k_hat as it is (docs/prognostics.md, "Life tracking"). Both are learned from
run-to-failure histories with their truth, which must not be the histories the track stage scores, so this stage
generates a life split of its own (the generate stage's settings and seed + 1, ``companions.life_actuators``
histories), tracks it with the truth to fit the response, trains and calibrates the near-nominal FDI on it and on
the store's near-nominal records (:func:`~phm_torch.tracking.near_nominal_training.train_near_nominal`), then tracks
it with both files under each end-of-life rule of the tracker and records the one to use (:func:`choose_end_of_life_rule`)
in the near-nominal FDI, which phm-track's ``verdict=auto`` / ``faulty_at=auto`` read.
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any

import torch
from omegaconf import DictConfig

from .. import provenance
from ..checks import number
from ..online.loaded import load_pipeline
from ..tracking import read_index
from ..tracking.companions import SUFFIXES
from ..tracking.near_nominal import TooFewNearNominalRecords
from ..tracking.near_nominal_training import NearNominalTraining, train_near_nominal
from ..tracking.response import RESPONSE_BINS, RESPONSE_MIN_COUNT, FDIResponse, probe_k_hat
from ..tracking.tracker_check import TrackerCheck
from . import common, schema
from .stage_config import compose_stage

log = logging.getLogger(__name__)
# the tracker's end-of-life rules tried (TrackerSettings.verdict, .faulty_at); the first is its default
RULES = (("record", "p50"), ("record", "p5"), ("posterior", "p50"), ("posterior", "p5"))
# an inspection interval flagged late (a faulty actuator left in service) costs this many flagged early (one removed
# that much before its end of life): a judgement, not a measurement; at 5 a rule one interval late on a fifth of the
# lives ties with one five intervals early on a fifth
LATE_WEIGHT = 5.0
OWN_KEYS = ("data_dir", "stage", "seed", "dataset.life.n_actuators")  # set by this stage for its life split
# the near-nominal training's code defaults under companions.near_nominal (conf/run.yaml composes them in first)
# and the end-of-life rule's LATE_WEIGHT as companions.late_weight
schema.register("run_companions", {"near_nominal": schema.node(NearNominalTraining()), "late_weight": LATE_WEIGHT})


def choose_end_of_life_rule(
    tracked: dict[tuple[str, str], dict[str, Any]], late_weight: float = LATE_WEIGHT
) -> dict[str, Any]:
    """The tracker's end-of-life rule (``verdict``, ``faulty_at``) for a pipeline, from its tracks of one life split
    under each rule of :data:`RULES` (phm-track's metrics, with the truth): the one whose ends of life are flagged
    least far outside one inspection interval, late counted ``late_weight`` times early (the mean intervals
    ``eol_intervals_early`` + ``late_weight`` x ``eol_intervals_late``, a life never flagged as late as its last
    inspection allows), the earlier in :data:`RULES` on a tie (the first is the tracker's default). How far counts,
    not only how often: on the ball-screw sketch ``record`` flagged 62 % of its ends of life early by up to 21
    intervals (its own verdict raises false alarms near nominal) and ``posterior/p5`` 15 % late by at most a quarter of
    one; counting shares alone chose the first. The posterior's median alone can flag late where the health
    classifier's boundary lies beyond phi_a's."""
    figures = {}
    for rule, m in tracked.items():
        t = m.get("tracker") or {}
        within, early = t.get("eol_flagged_within_one_inspection"), t.get("eol_flagged_early")
        late = None if within is None or early is None else max(0.0, 1.0 - within - early)
        off_early, off_late = t.get("eol_intervals_early"), t.get("eol_intervals_late")
        figures["/".join(rule)] = {
            "eol_flagged_within_one_inspection": within,
            "eol_flagged_early": early,
            "eol_flagged_late_or_never": late,
            "eol_intervals_early": off_early,
            "eol_intervals_late": off_late,
            "cost": None if off_early is None or off_late is None else off_early + late_weight * off_late,
            "prognostic_horizon": t.get("prognostic_horizon"),
            "alpha_lambda": t.get("alpha_lambda"),
        }
    scored = {rule: f for rule, f in zip(tracked, figures.values()) if f["cost"] is not None}
    if not scored:
        chosen = next(iter(tracked))
    else:
        chosen = min(scored, key=lambda r: (round(scored[r]["cost"], 9), RULES.index(r)))
    return {"verdict": chosen[0], "faulty_at": chosen[1], "rules": figures, "late_weight": late_weight}


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
    late_weight = number(node.get("late_weight", LATE_WEIGHT), "companions.late_weight", 0.0)
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
    n_rows = sum(len(rows) for rows in read_index(life / "index.csv").values())
    fit = n_rows >= RESPONSE_BINS * RESPONSE_MIN_COUNT
    if not fit:
        log.warning(
            "companions: %d inspections are too few to fit the FDI response (%d needed): none written; the tracker "
            "reads the pipeline's k_hat without it (companions.life_actuators=%d: give more histories)",
            n_rows,
            RESPONSE_BINS * RESPONSE_MIN_COUNT,
            n_actuators,
        )
    life_args = [
        *shared,
        *damage,
        f"index={life / 'index.csv'}",
        f"pipeline={pipeline}",
        f"truth={life / 'truth.json'}",
    ]
    raw, _ = track(  # the pipeline's own k_hat against the truth, for the response (the particles do not matter)
        compose_stage(
            "track",
            [
                *life_args,
                f"out_dir={root / 'track_raw'}",
                "response=null",
                "near_nominal=null",
                "n_particles=16",
                "rul_particles=16",
                *([f"response_out={paths['response']}"] if fit else []),
            ],
        )
    )
    previous = torch.get_num_threads()
    torch.set_num_threads(threads)
    try:
        store = data_dir if (data_dir / "dataset.h5").is_file() else None
        net, report = train_near_nominal(pipeline, life, settings, store)
    except TooFewNearNominalRecords as err:
        # too few histories near nominal (a robust actuator's lives leave it early): the run goes on without this
        # file, as phm-track does, and says which setting gives more
        log.warning(
            "companions: %s: no near-nominal FDI written; the tracker reads the pipeline's k_hat near nominal too "
            "(companions.life_actuators=%d: give more histories, or companions.near_nominal.holdout / gate to "
            "calibrate on more of them)",
            err,
            n_actuators,
        )
        # the end-of-life rule is still chosen, on the tracker as phm-track will run it (the response alone), and
        # recorded in the tracker check, which phm-track's verdict=auto / faulty_at=auto then read
        chosen, check = check_tracker(pipeline, life_args, root, "null", late_weight)
        return {
            **_metrics(n_actuators, seed, raw, gen_metrics, paths, fit, skipped=str(err)),
            **check,
            "tracker_rule": chosen,
        }
    finally:
        torch.set_num_threads(previous)
    net.save(paths["near_nominal"])
    # the tracker as the track stage will run it (both files beside the pipeline) under each end-of-life rule; the
    # rule chosen is recorded in the near-nominal FDI (phm-track verdict=auto). Most of these histories trained it:
    # its reading is sharper on them than on new ones, so a rule's flags look later here than they will be
    chosen, check = check_tracker(pipeline, life_args, root, "auto", late_weight)
    net.provenance["tracker_rule"] = chosen
    net.save(paths["near_nominal"])
    log.info("companions of %s: %s", pipeline, ", ".join(str(p) for p in paths.values() if p.is_file()))
    return {
        **_metrics(n_actuators, seed, raw, gen_metrics, paths, fit),
        **check,
        "tracker_rule": chosen,
        "near_nominal": str(paths["near_nominal"]),
        "near_nominal_settings": {k: common.plain(v) for k, v in vars(settings).items()},
        "near_nominal_records": {"life": report["life_records"], "store": report["store_records"]},
        "near_nominal_heldout_rms": report["heldout"],
    }


def check_tracker(
    pipeline: Path, life_args: list[str], root: Path, near_nominal: str, late_weight: float = LATE_WEIGHT
) -> tuple[dict[str, Any], dict[str, Any]]:
    """Track a life split (``life_args``: phm-track's overrides naming it and ``pipeline``) under each end-of-life rule
    of :data:`RULES` with the FDI response beside the pipeline and ``near_nominal`` (``auto`` | ``null``), choose the
    rule (:func:`choose_end_of_life_rule`) and write the tracker check of it beside the pipeline; the tracks go under
    ``root``. Returns the chosen rule with every rule's figures, and the metrics of the check written."""
    tracked = _tracked_by_rule(life_args, root, near_nominal)
    chosen = choose_end_of_life_rule(tracked, late_weight)
    rule = {key: chosen[key] for key in ("verdict", "faulty_at")}
    check = _tracker_check(pipeline, companion_paths(pipeline), tracked[(rule["verdict"], rule["faulty_at"])], rule)
    return chosen, check


def _tracked_by_rule(life_args: list[str], root: Path, near_nominal: str) -> dict[tuple[str, str], dict[str, Any]]:
    """phm-track's metrics of this stage's life split under each end-of-life rule of :data:`RULES`, with the FDI
    response beside the pipeline and ``near_nominal`` (``auto``: the file beside it; ``null``: none)."""
    from .track import track

    return {
        rule: track(
            compose_stage(
                "track",
                [
                    *life_args,
                    f"out_dir={root / ('track_' + '_'.join(rule))}",
                    "response=auto",
                    f"near_nominal={near_nominal}",
                    f"verdict={rule[0]}",
                    f"faulty_at={rule[1]}",
                    "timing_align=false",  # on time: the share the scan reads off is the pipeline's own (tracker check)
                ],
            )
        )[0]
        for rule in RULES
    }


def _tracker_check(
    pipeline: Path, paths: dict[str, Path], tracked: dict[str, Any], rule: dict[str, str]
) -> dict[str, Any]:
    """Write the tracker's figures on this stage's life split (phm-track's metrics ``tracked``, under ``rule``)
    beside the pipeline, where phm-track's ``tracker_check=auto`` reads them; the stage's metrics of it."""
    loaded = load_pipeline(pipeline)
    prov = loaded.metadata.get("provenance") or {}
    made_for = {
        "source": str(pipeline),
        "probe_k_hat": probe_k_hat(loaded.module),
        "actuator": provenance.describe(prov.get("actuator")),
        "command": provenance.describe(prov.get("command")),
    }
    check = TrackerCheck.from_metrics(tracked, rule, made_for)
    check.save(paths["tracker_check"])
    for line in check.warnings():
        log.warning("companions: %s", line)
    return {"tracker_check": str(paths["tracker_check"]), "tracker_check_figures": dict(check.figures)}


def _metrics(
    n_actuators: int,
    seed: int,
    raw: dict[str, Any],
    gen_metrics: dict[str, Any],
    paths: dict[str, Path],
    fit: bool,
    skipped: str | None = None,
) -> dict[str, Any]:
    """The stage's metrics every outcome shares; ``skipped``: why no near-nominal FDI was written (None: it was)."""
    response = FDIResponse.load(paths["response"]) if fit else None
    out = {
        "life_actuators": n_actuators,
        "life_seed": seed,
        "life_inspections": raw["inspections"],
        "life_generate": gen_metrics.get("life"),
        "response": None if response is None else str(paths["response"]),
        "response_corrected": None if response is None else response.corrected,
    }
    if skipped is not None:
        out.update(near_nominal=None, near_nominal_skipped=skipped, tracker_rule=None)
    return out
