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

import json
import logging
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import hydra
from omegaconf import DictConfig

from ..online.command_check import check_command
from ..workbench import (
    ClosureSettings,
    DiagnosticSettings,
    FitSettings,
    HighBandNoise,
    ScoreSettings,
    Workbench,
    WorkbenchSettings,
    write_report,
)
from . import common

log = logging.getLogger(__name__)


def _mapping(value: Any, name: str) -> dict:
    value = common.plain(value)
    if value is None:
        return {}
    if not isinstance(value, Mapping):
        raise ValueError(f"{name} must be a mapping, got {value!r}")
    return dict(value)


def _names(value: Any, name: str, allow_none: bool = False) -> list[str] | None:
    value = common.plain(value)
    if value is None and allow_none:
        return None
    if isinstance(value, str):
        value = [value]
    if not isinstance(value, list) or not all(isinstance(v, str) and v for v in value):
        raise ValueError(f"{name} must be a list of names, got {value!r}")
    return list(value)


def _numbers(value: Any, name: str, minimum: float | None = None, strict: bool = False) -> tuple[float, ...]:
    value = common.plain(value)
    if not isinstance(value, list) or not value:
        raise ValueError(f"{name} must be a non-empty list of numbers, got {value!r}")
    return tuple(common.number(v, f"{name}[{i}]", minimum, strict) for i, v in enumerate(value))


def _fit(node: Any, name: str, defaults: FitSettings) -> FitSettings:
    d = _mapping(node, name)
    known = {"max_iter", "lambdas", "damping", "tol_abs", "tol_rel"}
    bad = sorted(set(d) - known - {"top", "rounds", "free", "ratio"})
    if bad:
        raise ValueError(f"{name}: unknown key(s) {bad}; known: {sorted(known)}")
    return FitSettings(
        max_iter=common.integer(d.get("max_iter", defaults.max_iter), f"{name}.max_iter", 1),
        lambdas=_numbers(d["lambdas"], f"{name}.lambdas", 0.0, True) if "lambdas" in d else defaults.lambdas,
        damping=common.number(d.get("damping", defaults.damping), f"{name}.damping", 0.0, True),
        tol_abs=common.number(d.get("tol_abs", defaults.tol_abs), f"{name}.tol_abs", 0.0),
        tol_rel=common.number(d.get("tol_rel", defaults.tol_rel), f"{name}.tol_rel", 0.0))


def settings_from_config(cfg: DictConfig) -> tuple[WorkbenchSettings, HighBandNoise]:
    """The loop's settings from the composed config; every error names the config field."""
    score = _mapping(cfg.get("score"), "score")
    grid = _mapping(score.get("grid"), "score.grid")
    for eff, g in grid.items():
        if not isinstance(g, Mapping):
            raise ValueError(f"score.grid.{eff} must be a mapping {{parameter: [values]}}, got {g!r}")
    grid = {eff: {k: _numbers(v, f"score.grid.{eff}.{k}") for k, v in g.items()} for eff, g in grid.items()}
    sc = ScoreSettings(step=common.number(score.get("step", 0.1), "score.step", 0.0, True),
                       hac_lags=common.integer(score.get("hac_lags", 200), "score.hac_lags", 0),
                       alpha=common.number(score.get("alpha", 0.01), "score.alpha", 0.0, True),
                       grid=grid, alias_ratio=common.number(score.get("alias_ratio", 1e-3), "score.alias_ratio", 0.0),
                       rank_tol=common.number(score.get("rank_tol", 1e-3), "score.rank_tol", 0.0),
                       min_gain=common.number(score.get("min_gain", 0.01), "score.min_gain", 0.0),
                       data_orders=common.integer(score.get("data_orders", 3), "score.data_orders", 0))
    refit = _mapping(cfg.get("refit"), "refit")
    free = _mapping(refit.get("free"), "refit.free")
    closure = _mapping(cfg.get("closure"), "closure")
    harmonics = closure.get("harmonics")  # null: from the actuator's orders and the residual's
    if harmonics is not None and not isinstance(harmonics, list):
        raise ValueError(f"closure.harmonics must be null or a list of orders, got {harmonics!r}")
    cl = ClosureSettings(
        enabled=str(closure.get("enabled", "auto")), equation=str(closure.get("equation", "torque")),
        harmonics=None if harmonics is None else tuple(common.integer(h, f"closure.harmonics[{i}]", 1)
                                                       for i, h in enumerate(harmonics)),
        data_orders=common.integer(closure.get("data_orders", 3), "closure.data_orders", 0),
        hidden=common.integer(closure.get("hidden", 8), "closure.hidden", 0),
        output_scale=common.number(closure.get("output_scale", 1e-3), "closure.output_scale", 0.0, True),
        ridge=common.number(closure.get("ridge", 1.0), "closure.ridge", 0.0),
        fd_step=common.number(closure.get("fd_step", 0.05), "closure.fd_step", 0.0, True),
        ratio=common.number(closure.get("ratio", 1.5), "closure.ratio", 0.0, True),
        seed=common.integer(closure.get("seed", 0), "closure.seed", 0),
        fit=_fit({k: v for k, v in closure.items() if k in ("max_iter", "lambdas")}, "closure",
                 FitSettings(max_iter=4, lambdas=(1.0,))))
    ds = _diagnostics(_mapping(cfg.get("diagnostics"), "diagnostics"))
    noise = _mapping(cfg.get("noise"), "noise")
    band = _numbers(noise.get("band", [0.25, 0.5]), "noise.band", 0.0)
    if len(band) != 2:
        raise ValueError(f"noise.band must be [low, high], got {list(band)}")
    hb = HighBandNoise((band[0], band[1]), common.integer(noise.get("segment", 256), "noise.segment", 16))
    settings = WorkbenchSettings(
        calibration=_fit(cfg.get("calibration"), "calibration", FitSettings()),
        refit=_fit(refit, "refit", FitSettings(max_iter=6)), score=sc, diagnostics=ds, closure=cl,
        refit_top=common.integer(refit.get("top", 3), "refit.top", 0),
        rounds=common.integer(refit.get("rounds", 2), "refit.rounds", 0),
        refit_free={k: _names(v, f"refit.free.{k}") for k, v in free.items()},
        library=_names(cfg.get("library"), "library", allow_none=True),
        before_after=bool(cfg.get("before_after", True)),
        fd_step=common.number(cfg.get("fd_step", 1e-2), "fd_step", 0.0, True))
    return settings, hb


def _diagnostics(node: dict) -> DiagnosticSettings:
    defaults = DiagnosticSettings()
    values = {}
    for key, v in node.items():
        if not hasattr(defaults, key):
            raise ValueError(f"diagnostics: unknown key {key!r}; known: {sorted(vars(defaults))}")
        if key == "max_harmonic":  # null: twice the actuator's highest structural order
            values[key] = None if v is None else common.integer(v, "diagnostics.max_harmonic", 1)
        elif isinstance(getattr(defaults, key), int):
            values[key] = common.integer(v, f"diagnostics.{key}", 1)
        else:
            values[key] = common.number(v, f"diagnostics.{key}", 0.0, strict=True)
    return DiagnosticSettings(**values)


def build_workbench(cfg: DictConfig) -> Workbench:
    """The :class:`Workbench` of the composed config (validated; no simulation yet)."""
    params = common.actuator(cfg)
    fid = common.fidelity(cfg.fidelity)
    faults = common.fault_vector(cfg.get("faults", list(params.nominal_faults)))
    effects = common.effects(cfg.get("effects"))  # validates names and values like phm-simulate
    spec = {e.name: {k: float(v) for k, v in e.values.items()} for e in effects}
    groups = {k: _names(v, f"groups.{k}") for k, v in _mapping(cfg.get("groups"), "groups").items()}
    bounds = _numbers(cfg.get("scale_bounds", [0.2, 5.0]), "scale_bounds", 0.0, True)
    if len(bounds) != 2:
        raise ValueError(f"scale_bounds must be [min, max], got {list(bounds)}")
    channels = _names(cfg.get("channels", ["position", "current"]), "channels")
    settings, noise = settings_from_config(cfg)
    n_threads = cfg.get("threads", 1)
    n_threads = None if n_threads is None else common.integer(n_threads, "threads", 1)
    name = common.choice(cfg, "actuator") or "custom"   # the report's provenance
    return Workbench(params, fid, spec, _names(cfg.get("free", []), "free"), groups, faults, channels, settings,
                     noise, (bounds[0], bounds[1]), common.device(cfg.get("device", "cpu")), n_threads, name)


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


def run_workbench(cfg: DictConfig) -> tuple[dict[str, Any], dict[str, Any]]:
    """Run the whole loop on the configured measurements and write the report.

    Returns:
        ``metrics``: the report's headline numbers (NRMSE and noise floor before/after, best candidate,
        timing, files); ``objects``: ``result`` (:class:`WorkbenchResult`), ``report`` (the JSON dict),
        ``workbench``, ``paths``.
    """
    wb = build_workbench(cfg)
    measurements = common.plain(cfg.measurements)
    records = wb.load(measurements, resample=bool(cfg.get("resample", False)))
    command = command_provenance(cfg, records)
    out_dir = Path(str(cfg.get("out_dir", "results/workbench"))).expanduser()
    result = wb.run(records)
    paths = write_report(result, out_dir, plot=bool(cfg.get("plot", True)))
    report = json.loads(paths["report.json"].read_text())
    report["command"] = command
    common.write_json(paths["report.json"], report)
    best = next((c for c in report["candidates"] if c["significant"]), None)
    metrics = {"nrmse": report["nrmse"], "noise_floor": report["noise_floor"],
               "best_candidate": best["effect"] if best else None,
               "nrmse_after": report["final"]["nrmse"], "added": report["added"],
               "closure_lead": report["closure"]["lead"] if report["closure"] else None,
               "timing": report["timing"], "report": str(paths["report.json"]),
               "html": str(paths.get("report.html")) if "report.html" in paths else None}
    return metrics, {"result": result, "report": report, "workbench": wb, "paths": paths}


@hydra.main(config_path=common.CONFIG_PATH, config_name="workbench", version_base="1.3")
@common.report_errors("phm-workbench")
def main(cfg: DictConfig) -> None:
    metrics, _ = run_workbench(cfg)
    log.info("wrote %s", metrics["report"])
    print(json.dumps(metrics, indent=2), flush=True)


if __name__ == "__main__":
    main()
