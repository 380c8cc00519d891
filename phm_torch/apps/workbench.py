"""``phm-workbench``: compare the model with measurements, locate where it fails, rank the missing physical
effect, add it and watch the error fall.

Examples::

    phm-workbench measurements=examples/workbench_hidden_cogging.csv out_dir=results/wb
    phm-workbench 'measurements=[a.csv,b.csv]' fidelity=hf
    phm-workbench measurements=run.csv '+effects.cogging_torque={}'      # the model with that effect

Writes ``out_dir/report.json``, ``report.html`` (figures embedded) and the PNG figures. The work is done by
:func:`run_workbench` (a plain function of the composed config, returning ``(metrics, objects)``); :func:`main`
is the thin Hydra entry point.
"""

from __future__ import annotations

import inspect
import json
import logging
from pathlib import Path
from typing import Any

import hydra
from omegaconf import DictConfig, OmegaConf

from .. import checks, provenance
from ..online.command_check import check_command
from ..workbench import (
    ClosureSettings,
    DiagnosticSettings,
    FitSettings,
    HighBandNoise,
    RefitSettings,
    ScoreSettings,
    Workbench,
    WorkbenchSettings,
    write_report,
)
from . import common, schema

log = logging.getLogger(__name__)

# config node -> the settings dataclass it instantiates (the home of its defaults)
SETTINGS_NODES = {
    "calibration": FitSettings,
    "refit": RefitSettings,
    "score": ScoreSettings,
    "closure": ClosureSettings,
    "diagnostics": DiagnosticSettings,
    "noise": HighBandNoise,
}
LOOP_KEYS = ("library", "before_after", "fd_step")  # WorkbenchSettings' own fields
MODEL_KEYS = ("fidelity", "effects", "free", "groups", "faults", "channels", "scale_bounds", "device", "threads")
CALL_KEYS = {"resample": Workbench.load, "plot": write_report}  # keyword arguments of the calls the app makes


def code_defaults() -> dict[str, Any]:
    """Every workbench setting at its code default, as the config tree ``conf/workbench.yaml`` composes in
    (``/schema/workbench``): one node per settings dataclass (:data:`SETTINGS_NODES`), the loop's own fields
    (:class:`WorkbenchSettings`), the model's (the :class:`Workbench` constructor's defaults) and those of
    the calls (:data:`CALL_KEYS`)."""
    loop = WorkbenchSettings()
    model = inspect.signature(Workbench).parameters
    return {
        **{key: schema.node(cls()) for key, cls in SETTINGS_NODES.items()},
        **{key: schema.plain(getattr(loop, key)) for key in LOOP_KEYS},
        **{key: schema.plain(model[key].default) for key in MODEL_KEYS},
        **{key: inspect.signature(call).parameters[key].default for key, call in CALL_KEYS.items()},
    }


schema.register("workbench", code_defaults())


def settings_from_config(cfg: DictConfig) -> tuple[WorkbenchSettings, HighBandNoise]:
    """The loop's settings from the composed config (or ``conf/workbench.yaml`` as loaded: the code defaults
    fill what it does not set); each node is instantiated, every error names the config field."""
    given = {key: cfg[key] for key in (*SETTINGS_NODES, *LOOP_KEYS) if key in cfg}
    tree = OmegaConf.merge({key: code_defaults()[key] for key in (*SETTINGS_NODES, *LOOP_KEYS)}, given)
    nodes = {key: common.build(tree[key], key) for key in SETTINGS_NODES}
    settings = WorkbenchSettings.of(
        nodes["refit"],
        calibration=nodes["calibration"],
        score=nodes["score"],
        closure=nodes["closure"],
        diagnostics=nodes["diagnostics"],
        **{key: common.plain(tree[key]) for key in LOOP_KEYS},
    )
    return settings, nodes["noise"]


def build_workbench(cfg: DictConfig) -> Workbench:
    """The :class:`Workbench` of the composed config (validated; no simulation yet)."""
    params = common.actuator(cfg)
    fid = common.fidelity(cfg.fidelity)
    faults = None if cfg.faults is None else common.fault_vector(cfg.faults)  # None: the actuator's nominal
    effects = common.effects(cfg.effects, params)  # validates names and values like phm-simulate
    spec = {e.name: {k: float(v) for k, v in e.values.items()} for e in effects}
    groups = {k: checks.names(v, f"groups.{k}") for k, v in checks.mapping(common.plain(cfg.groups), "groups").items()}
    bounds = checks.numbers(common.plain(cfg.scale_bounds), "scale_bounds", 0.0, True)
    if len(bounds) != 2:
        raise ValueError(f"scale_bounds must be [min, max], got {list(bounds)}")
    channels = checks.names(common.plain(cfg.channels), "channels")
    settings, noise = settings_from_config(cfg)
    n_threads = None if cfg.threads is None else common.integer(cfg.threads, "threads", 1)
    name = common.choice(cfg, "actuator") or "custom"  # the report's provenance
    return Workbench(
        params,
        fid,
        spec,
        checks.names(common.plain(cfg.free), "free"),
        groups,
        faults,
        channels,
        settings,
        noise,
        (bounds[0], bounds[1]),
        common.device(cfg.device),
        n_threads,
        name,
    )


def command_provenance(cfg: DictConfig, records: list[Any]) -> dict[str, Any]:
    """The test command of the report: the chosen ``command=`` (its record, and each file's command column
    checked against it: a record of another command is an error naming the file) or, without one, the
    files' own command columns (the model is driven by them either way)."""
    requested = common.requested_provenance(cfg)["command"]
    if requested is None:
        return {"name": "measured", "source": "each measurement file's command column"}
    command = common.command(cfg.command)
    for record in records:
        check = check_command(record.command, command(record.time.double()), record.sample_rate)
        if not check.ok:
            raise ValueError(f"command={requested['name']}: {record.path or record.name}: {check.reason()}")
    return requested


def check_recorded_actuator(cfg: DictConfig, records: list[Any]) -> None:
    """A measurement file that says which actuator it was recorded on (a sidecar ``<file>.json`` with a
    ``provenance`` record, as the shipped demo has) must be of the actuator the model is built from, chosen or
    default: a difference is an error naming both (compared with another datasheet, its record passes every file
    check and the report blames missing physics)."""
    used = {"actuator": common.requested_provenance(cfg)["actuator"]}
    for record in records:
        sidecar = Path(record.path).with_suffix(".json") if record.path is not None else None
        if sidecar is None or not sidecar.is_file():
            continue
        recorded = json.loads(sidecar.read_text()).get("provenance") or {}
        if recorded.get("actuator") is not None:
            provenance.require_same({"actuator": recorded["actuator"]}, used, f"measurement {record.path}")


def run_workbench(cfg: DictConfig) -> tuple[dict[str, Any], dict[str, Any]]:
    """Run the whole loop on the configured measurements and write the report.

    Returns:
        ``metrics``: the report's headline numbers (NRMSE and noise floor before/after, best candidate,
        timing, files); ``objects``: ``result`` (:class:`WorkbenchResult`), ``report`` (the JSON dict),
        ``workbench``, ``paths``.
    """
    wb = build_workbench(cfg)
    measurements = common.plain(cfg.measurements)
    records = wb.load(measurements, resample=bool(cfg.resample))
    check_recorded_actuator(cfg, records)
    command = command_provenance(cfg, records)
    out_dir = Path(str(cfg.out_dir)).expanduser()
    result = wb.run(records)
    paths = write_report(result, out_dir, plot=bool(cfg.plot))
    report = json.loads(paths["report.json"].read_text())
    report["command"] = command
    common.write_json(paths["report.json"], report)
    best = next((c for c in report["candidates"] if c["significant"]), None)
    metrics = {
        "nrmse": report["nrmse"],
        "noise_floor": report["noise_floor"],
        "best_candidate": best["effect"] if best else None,
        "nrmse_after": report["final"]["nrmse"],
        "added": report["added"],
        "closure_lead": report["closure"]["lead"] if report["closure"] else None,
        "timing": report["timing"],
        "report": str(paths["report.json"]),
        "html": str(paths.get("report.html")) if "report.html" in paths else None,
    }
    return metrics, {"result": result, "report": report, "workbench": wb, "paths": paths}


def default_actuator_note(overrides: list[str], name: str | None) -> str | None:
    """The warning for measurements compared with the app's default datasheet because no ``actuator=`` was given
    (a record of another actuator at the same sample rate passes every file check and is misread); None when one
    was given (``overrides``: the command line's Hydra overrides)."""
    if any(o.lstrip("+~").split("=", 1)[0] == "actuator" for o in overrides):
        return None
    return (
        f"no actuator= given: the measurements are compared with the default datasheet {name}; for your own "
        "actuator give actuator=<name> with its folder on hydra.searchpath (docs/own_actuator.md)"
    )


@hydra.main(config_path=common.CONFIG_PATH, config_name="workbench", version_base="1.3")
@common.report_errors("phm-workbench")
def main(cfg: DictConfig) -> None:
    from hydra.core.hydra_config import HydraConfig

    note = default_actuator_note(list(HydraConfig.get().overrides.task), common.choice(cfg, "actuator"))
    if note:
        log.warning(note)
    metrics, _ = run_workbench(cfg)
    log.info("wrote %s", metrics["report"])
    print(json.dumps(metrics, indent=2), flush=True)


if __name__ == "__main__":
    main()
