"""``phm-run``: the main job, every stage of phm_torch end to end, and a report against the seed paper.

Stages (each the plain function of its own app, composed from its own config plus the overrides listed
under its name in conf/run.yaml): cases (virtual bench), generate (with a life split of run-to-failure
histories), train, evaluate (RUL + TorchScript export and reload), companions (the tracker's FDI response and
near-nominal FDI of that pipeline, from histories of their own: :mod:`.run_companions`), track (phm-track on the
life split: the fused RUL against the single-record one), workbench (hidden-effect demo), report
(report/index.html). ``metrics.json`` merges
every stage's metrics under the stage's name.
"""

from __future__ import annotations

import json
import logging
import time
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import hydra
import torch
from omegaconf import DictConfig

from .. import provenance
from ..data.store import DatasetStore
from ..faults import FAULT_NAMES
from ..params import CONF_DIR
from ..report.figures import err_alpha_vs_modes, fdi_per_parameter, hidden_neuron_study, placement
from ..report.paper import build_report
from ..surrogates.bundle import SurrogateBundle
from ..timing import torchscript_step_latency
from . import common
from .run_companions import remove_stale, run_companions
from .stage_config import (
    SHARED_GROUPS,
    compose_stage,
    damage_overrides,
    dropped_defaults,
    generate_overrides,
    shared_overrides,
    stage_overrides,
)

log = logging.getLogger(__name__)
STAGES = ("cases", "generate", "train", "evaluate", "companions", "track", "workbench", "report")


def workbench_measurement(cfg: DictConfig, shared: list[str], out_dir: Path) -> Path:
    """The hidden-effect record the workbench stage diagnoses: the shipped example when the run's actuator and
    command are the ones it was recorded with (its sidecar JSON says which), else one simulated now (HF) of
    the run's actuator on its command, with the hidden effect scaled to that actuator (``workbench_demo``)."""
    demo = cfg.workbench_demo
    shipped = CONF_DIR.parent / str(demo.shipped)
    sidecar = json.loads(shipped.with_suffix(".json").read_text()) if shipped.with_suffix(".json").is_file() else {}
    requested = common.requested_provenance(cfg)
    recorded = sidecar.get("provenance") or {}
    if shipped.is_file() and all(
        (recorded.get(k) or {}).get("sha256") == (requested[k] or {}).get("sha256") for k in SHARED_GROUPS
    ):
        return shipped
    from .simulate import simulate_to_csv

    params = common.actuator(cfg)
    effect = str(demo.effect)
    amplitude = (
        common.number(
            demo.amplitude_per_coulomb_friction, "workbench_demo.amplitude_per_coulomb_friction", 0.0, strict=True
        )
        * params.coulomb_friction
    )
    noise = common.number(demo.current_noise_per_limit, "workbench_demo.current_noise_per_limit", 0.0)
    # the position noise follows the command's size, so an actuator whose user side is in metres (a ball screw)
    # gets as clean a position channel as the reference (2e-5 rad on its 5e-3 rad chirp)
    cmd = common.command(cfg.command)
    peak = float(cmd(torch.linspace(0.0, float(cmd.duration), 20001, dtype=torch.float64)).abs().max())
    position_noise = (
        common.number(demo.position_noise_per_command, "workbench_demo.position_noise_per_command", 0.0) * peak
    )
    out = out_dir / f"hidden_{effect}.csv"
    print(
        f"[phm-run] workbench: simulating a record of {common.choice(cfg, 'actuator')} with a hidden {effect} "
        f"(amplitude {amplitude:.3g} N m) -> {out}",
        flush=True,
    )
    simulate_to_csv(
        compose_stage(
            "simulate",
            [
                *shared,
                "fidelity=hf",
                f"+effects.{effect}.amplitude={amplitude}",
                *(f"+effects.{effect}.{k}={json.dumps(v)}" for k, v in (common.plain(demo.params) or {}).items()),
                f"seed={common.integer(demo.seed, 'workbench_demo.seed', 0)}",
                f"noise.current={noise * params.current_limit}",
                f"noise.position={position_noise}",
                f"out={out}",
                "plot=false",
            ],
        )
    )
    return out


def pretrained_study(cfg: DictConfig, run_dir: Path, metrics: dict[str, Any]) -> dict[str, Any] | None:
    """The shipped pipeline ``cfg.report.pretrained`` run by phm-predict on ``cfg.report.pretrained_records`` and
    on the cases stage's records (when they have the pipeline's test length), for the report's section
    (:mod:`phm_torch.report.pretrained` documents the dict). Not run (``skipped`` says why) for a run of
    another actuator or command than the pipeline's: its figures would be outside its domain."""
    from ..online.export import read_metadata
    from .predict import predict

    if cfg.report.get("pretrained") is None:
        return None
    pipeline = _shipped(str(cfg.report.pretrained))
    study: dict[str, Any] = {"pipeline": str(cfg.report.pretrained), "skipped": None, "notes": [], "records": []}
    if not pipeline.is_file():
        return {**study, "skipped": f"report.pretrained: no file {str(pipeline)!r}"}
    recorded = read_metadata(pipeline).get("provenance") or {}
    study.update(
        actuator=provenance.describe(recorded.get("actuator")), command=provenance.describe(recorded.get("command"))
    )
    requested = common.requested_provenance(cfg)
    for key in SHARED_GROUPS:
        if (recorded.get(key) or {}).get("sha256") != (requested[key] or {}).get("sha256"):
            return {
                **study,
                "skipped": f"it is for the {key} {study[key]}, this run's is {provenance.describe(requested[key])}",
            }
    files: list[tuple[Path, str, dict[str, float] | None]] = []
    for item in common.plain(cfg.report.get("pretrained_records")) or []:
        path = _shipped(str(item))
        sidecar = json.loads(path.with_suffix(".json").read_text()) if path.with_suffix(".json").is_file() else {}
        hidden = "; ".join(
            f"hidden {name} " + ", ".join(f"{k} {v:g}" for k, v in values.items())
            for name, values in (sidecar.get("hidden_effect") or {}).items()
        )
        files.append((path, f"bundled example {item}" + (f" ({hidden})" if hidden else ""), None))
    cases = metrics.get("cases") or {}
    command = (recorded.get("command") or {}).get("params") or {}
    if cases and cases.get("duration") == command.get("duration"):
        nominal = (cases.get("nominal") or {}).get("faults") or []
        for name, case in {"nominal": cases.get("nominal") or {}, **(cases.get("cases") or {})}.items():
            faults = case.get("faults") or []
            true = {FAULT_NAMES[i]: v for i, v in enumerate(faults) if i >= len(nominal) or v != nominal[i]}
            files.append(
                (
                    run_dir / "cases" / str(case.get("csv")),
                    (f"virtual bench ({cases.get('fidelity')}, noise-free): {name}"),
                    true,
                )
            )
    elif cases:
        study["notes"].append(
            f"The virtual bench's records are left out: they last {cases.get('duration')} s, the "
            f"pipeline's test record {command.get('duration')} s."
        )
    files = [f for f in files if f[0].is_file()]
    if not files:
        return {**study, "skipped": "no record to run it on"}
    _, objects = predict(
        compose_stage("predict", [f"pipeline={pipeline}", f"measurements={json.dumps([str(f[0]) for f in files])}"])
    )
    study["records"] = [
        {"name": path.name, "source": source, "true_k": true, "prediction": pred}
        for (path, source, true), pred in zip(files, objects["records"])
    ]
    return study


def _shipped(path: str) -> Path:
    """``path`` as given when it exists, else the file of that name shipped with the repository."""
    shipped = CONF_DIR.parent / path
    return Path(path) if Path(path).exists() or not shipped.exists() else shipped


def _studies(
    cfg: DictConfig, run_dir: Path, data_dir: Path, train_dir: Path, eval_dir: Path, metrics: dict[str, Any]
) -> dict[str, Any]:
    fig_dir = run_dir / "report"
    fig_dir.mkdir(parents=True, exist_ok=True)
    studies: dict[str, Any] = {"pretrained": pretrained_study(cfg, run_dir, metrics)}
    bundle_path = train_dir / "surrogates.pt"
    if bundle_path.is_file() and (data_dir / "manifest.json").is_file():
        bundle = SurrogateBundle.load(bundle_path)
        with DatasetStore(data_dir) as store:
            tr, va = store.split("train"), store.split("val")
            n_tr = min(len(tr), 2000)
            ktr, ytr = torch.as_tensor(tr.K[:n_tr]), torch.as_tensor(tr.current[:n_tr])
            kva, yva = torch.as_tensor(va.K[()]), torch.as_tensor(va.current[()])
            healthy = [int(store.split(s).healthy[()].sum()) for s in ("train", "val")]
            studies["healthy_fraction"] = healthy[0] / max(len(tr), 1)
        studies["err_alpha"] = err_alpha_vs_modes(bundle, yva, fig_dir / "err_alpha_vs_modes.png")
        studies["placement"] = placement(bundle, bundle.sample_rate, fig_dir / "placement.png")
        sizes = [common.integer(h, "report.hidden_neurons[]", 1) for h in common.plain(cfg.report.hidden_neurons)]
        studies["hidden"] = {
            "rows": hidden_neuron_study(
                bundle,
                ytr,
                ktr,
                yva,
                kva,
                sizes,
                common.integer(cfg.report.hidden_epochs, "report.hidden_epochs", 1),
                fig_dir / "hidden_neurons.png",
            ),
            "figure": fig_dir / "hidden_neurons.png",
        }
        if metrics.get("train", {}).get("fdi_mae"):
            studies["fdi_per_parameter"] = fdi_per_parameter(metrics["train"]["fdi_mae"], fig_dir / "fdi_mae.png")
        model = eval_dir / "online.pt"
        if model.is_file():
            studies["latency"] = torchscript_step_latency(
                model, yva, common.integer(cfg.report.latency_repeats, "report.latency_repeats", 10)
            )
    return studies


def run_all(cfg: DictConfig) -> tuple[dict[str, Any], dict[str, Any]]:
    """Run the configured stages under ``cfg.out_dir``; returns (merged metrics, objects)."""
    stages = common.plain(cfg.stages)
    if not isinstance(stages, list) or not stages:
        raise ValueError(f"stages must be a non-empty list from {list(STAGES)}, got {stages!r}")
    unknown = [s for s in stages if s not in STAGES]
    if unknown:
        raise ValueError(f"stages: unknown {unknown}; known: {list(STAGES)}")
    run_dir = Path(str(cfg.out_dir)).expanduser().resolve()
    run_dir.mkdir(parents=True, exist_ok=True)
    data_dir, train_dir, eval_dir = run_dir / "data", run_dir / "train", run_dir / "evaluate"
    gen_over = generate_overrides(cfg)
    shared = shared_overrides(cfg)
    damage = damage_overrides(cfg)
    for stage, lost in dropped_defaults(cfg).items():
        if stage in stages:
            keep = (
                "write data settings at the run level instead (phm-run +dataset.n_train=300), or repeat them"
                if stage == "generate"
                else "repeat them in your list to keep them"
            )
            log.warning(
                "%s: the run's list replaces conf/run.yaml's default list, so these defaults are not applied: %s (%s)",
                stage,
                ", ".join(lost),
                keep,
            )
    plan = {
        "cases": ("cases", [*shared, f"out_dir={run_dir / 'cases'}", *stage_overrides(cfg.cases, "cases")]),
        "generate": ("generate", [*shared, *damage, f"data_dir={data_dir}", *gen_over]),
        "train": (
            "train",
            [*shared, *damage, f"data_dir={data_dir}", f"out_dir={train_dir}", *stage_overrides(cfg.train, "train")],
        ),
        "evaluate": (
            "evaluate",
            [
                *shared,
                *damage,
                f"data_dir={data_dir}",
                f"bundle={train_dir / 'surrogates.pt'}",
                f"out_dir={eval_dir}",
                *stage_overrides(cfg.evaluate, "evaluate"),
            ],
        ),
        "track": (
            "track",
            [
                *shared,
                *damage,
                f"index={data_dir / 'life' / 'index.csv'}",
                f"pipeline={eval_dir / 'online.pt'}",
                f"truth={data_dir / 'life' / 'truth.json'}",
                f"out_dir={run_dir / 'track'}",
                *stage_overrides(cfg.track, "track"),
            ],
        ),
        "workbench": (
            "workbench",
            [*shared, f"out_dir={run_dir / 'workbench'}", *stage_overrides(cfg.workbench, "workbench")],
        ),
    }
    from .cases import run_cases
    from .evaluate import evaluate_rul
    from .generate import generate
    from .track import track
    from .train import train_surrogates
    from .workbench import run_workbench

    functions = {
        "cases": run_cases,
        "generate": generate,
        "train": train_surrogates,
        "evaluate": evaluate_rul,
        "track": track,
        "workbench": run_workbench,
    }
    # resumable: a run of some stages keeps the metrics of the stages run before in this out_dir (and the
    # report stage sees them); each stage run now replaces its own entry
    previous = run_dir / "metrics.json"
    metrics: dict[str, Any] = json.loads(previous.read_text()) if previous.is_file() else {}
    timings: dict[str, float] = dict(metrics.get("wall_s") or {})
    metrics["wall_s"] = timings  # the stages run so far, for the report's banner
    objects: dict[str, Any] = {}
    for i, stage in enumerate(stages, 1):
        log.info("[phm-run] stage %d/%d: %s", i, len(stages), stage)
        print(f"[phm-run] stage {i}/{len(stages)}: {stage}", flush=True)
        t0 = time.perf_counter()
        if stage == "report":
            studies = _studies(cfg, run_dir, data_dir, train_dir, eval_dir, metrics)
            metrics["report"] = {k: v for k, v in studies.items() if k in ("latency", "healthy_fraction")}
            metrics["report"]["hidden_neurons"] = studies.get("hidden", {}).get("rows")
            objects["report"] = build_report(run_dir, metrics, studies, repo=CONF_DIR.parent)
        elif stage == "companions":
            metrics[stage] = run_companions(cfg, run_dir, data_dir, eval_dir / "online.pt", shared, damage, gen_over)
        else:
            app, overrides = plan[stage]
            if stage == "track" and not (data_dir / "life" / "index.csv").is_file():
                raise ValueError(
                    f"stages: track needs the life split of the generate stage ({data_dir / 'life'} "
                    "has no index.csv); give the generate stage dataset.life.n_actuators > 0"
                )
            if stage == "workbench" and not any(o.startswith("measurements=") for o in overrides):
                overrides = [*overrides, f"measurements={workbench_measurement(cfg, shared, run_dir / 'workbench')}"]
            if stage == "evaluate":  # a new pipeline: the companion files of the one it replaces do not belong
                for path in remove_stale(eval_dir / "online.pt"):
                    log.info("removed %s (a companion of the pipeline this stage replaces)", path)
            stage_metrics, _ = functions[stage](compose_stage(app, overrides))
            metrics[stage] = stage_metrics
        timings[stage] = round(time.perf_counter() - t0, 2)
        print(f"[phm-run] {stage} done in {timings[stage]:.1f} s", flush=True)
        # after every stage, not once at the end: a later stage that fails, or a session that ends, keeps these
        common.write_json(run_dir / "metrics.json", json.loads(json.dumps(metrics, default=str)))
    return metrics, objects


# (stage, key path, label) of the figures phm-run prints at the end; every one is in metrics.json
SUMMARY = (
    ("train", ("err_k",), "err_k (val)"),
    ("train", ("classifier_accuracy",), "health classifier accuracy (val)"),
    ("evaluate", ("held_out_quality", "missed_faulty"), "verdict: faulty records answered healthy (held out)"),
    ("evaluate", ("held_out_quality", "false_alarm"), "verdict: healthy records answered faulty (held out)"),
    ("evaluate", ("fdi_not_identified",), "components the command does not identify"),
    ("evaluate", ("rul_band_coverage_full_flow",), "RUL band coverage, full flow"),
    ("evaluate", ("ood_fraction",), "held-out records out of distribution"),
    ("track", ("tracker", "coverage_5_95"), "life tracking: coverage of the 5-95 % band"),
    ("track", ("tracker", "eol_flagged_within_one_inspection"), "life tracking: ends of life flagged in time"),
    ("workbench", ("added",), "workbench: effects added"),
)


def summary(metrics: Mapping[str, Any]) -> dict[str, Any]:
    """The headline figures of a run's ``metrics`` (``SUMMARY``), those its stages produced."""
    out: dict[str, Any] = {}
    for stage, path, label in SUMMARY:
        value: Any = metrics.get(stage)
        for key in path:
            value = value.get(key) if isinstance(value, Mapping) else None
        if value is not None:
            out[label] = round(value, 4) if isinstance(value, float) else value
    return out


@hydra.main(config_path=common.CONFIG_PATH, config_name="run", version_base="1.3")
@common.report_errors("phm-run")
def main(cfg: DictConfig) -> None:
    metrics, objects = run_all(cfg)
    shown = {"report": str(objects.get("report")), "summary": summary(metrics), "wall_s": metrics["wall_s"]}
    print(json.dumps(shown, indent=2), flush=True)


if __name__ == "__main__":
    main()
