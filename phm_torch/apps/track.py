"""``phm-track``: life tracking of a fleet from its inspection records (:mod:`phm_torch.tracking`).

Reads the index CSV (``actuator,hours,file[,event]``), runs phm-predict's diagnosis on each record, fuses each
actuator's in-distribution inspections with a particle filter over (k, s) and writes ``track.json``
(per inspection: k_hat and its interval, the filtered k, the wear-rate scale, the tracker's RUL 5/50/95 % and
phm-predict's snapshot RUL, censored bounds null) and ``fleet.json`` (each actuator's latest state, by RUL 5 %,
with the pipeline, actuator and command it belongs to).
With ``truth=`` (a life split's truth.json) it scores both methods (:mod:`phm_torch.prognostics.life_metrics`)
into ``metrics.json`` and draws the figures. Rerun with the same settings to resume an interrupted run.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import logging
import math
from pathlib import Path
from typing import Any

import hydra
import torch
from omegaconf import DictConfig

from .. import provenance
from ..assessment_record import same_labels
from ..online.bench_check import check_bench
from ..online.diagnosis import contract_for
from ..online.loaded import TorchScriptPipeline, load_pipeline
from ..online.quality import held_out, quality_warnings
from ..online.record_corrections import prepare_record
from ..online.timing_tolerance import tolerance_seconds
from ..tracking import TrackerSettings, build_tracker, fleet_list, read_index, timing_spread, track_fleet
from ..tracking.companions import companion, missing_message
from ..tracking.fleet_check import FleetCheckSettings, check_fleet, probe_in_fleet, refused
from ..tracking.information_limit import information_limit, track_truth
from ..tracking.inspection import inspect_record
from ..tracking.near_nominal import NearNominalFDI
from ..tracking.response import fit_response, pairs_from_track, probe_k_hat
from ..tracking.state import fingerprint
from ..tracking.tracker_check import TrackerCheck
from . import common, schema
from .predict import _bench_nominal, _pipeline_command, _read, _record  # phm-predict's record path, reused as is

log = logging.getLogger(__name__)


def _tensors_sha256(state: dict[str, torch.Tensor]) -> str:
    """sha256 of a state dict's names and values (a companion network's identity in the run key)."""
    digest = hashlib.sha256()
    for name, value in sorted(state.items()):
        digest.update(name.encode())
        digest.update(value.detach().cpu().contiguous().numpy().tobytes())
    return digest.hexdigest()


def _sha256(path: Path) -> str:
    digest = hashlib.sha256()
    with open(path, "rb") as fh:
        for block in iter(lambda: fh.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


AUTO_KEYS = ("verdict", "faulty_at")  # "auto" in conf/track.yaml: the near-nominal FDI's recorded choice (auto_rule)
EARLY_WARNING = 0.5  # phm-track warns when the rule chosen flagged more of its companion split's ends of life early
# TrackerSettings' fields set at the top level of conf/track.yaml; their defaults are composed in from the
# dataclass (/schema/track), so the YAML does not restate them
TRACKER_KEYS = (
    "n_particles",
    "rul_particles",
    "seed",
    "measurement_dof",
    "resample_ess",
    "verdict",
    "verdict_evidence",
    "faulty_at",
    "boundary_std_hours",
    "new_spread",
)
schema.register(
    "track",
    {
        **{key: schema.plain(getattr(TrackerSettings(), key)) for key in TRACKER_KEYS},
        "fleet_check": {f.name: f.default for f in dataclasses.fields(FleetCheckSettings)},
    },
)


def _settings(
    cfg: DictConfig, near: NearNominalFDI | None = None, announce: bool = True, check: TrackerCheck | None = None
) -> TrackerSettings:
    values = {key: cfg[key] for key in TRACKER_KEYS}
    if values["measurement_dof"] in (".inf", "inf"):  # the command line's spelling of infinity
        values["measurement_dof"] = math.inf
    for key, value in auto_rule(near, announce, check).items():
        if values[key] == "auto":
            values[key] = value
    return TrackerSettings(**values)


def auto_rule(near: NearNominalFDI | None, announce: bool = True, check: TrackerCheck | None = None) -> dict[str, str]:
    """What ``verdict=auto`` and ``faulty_at=auto`` become: the rule the near-nominal FDI's maker chose on its own life
    split (phm-run's companions stage records ``tracker_rule`` in its provenance); without one, the rule of the
    tracker check beside the pipeline (the same stage chose it there when it could not train a near-nominal FDI);
    else the tracker's defaults (``record``, ``p50``)."""
    defaults = {key: getattr(TrackerSettings(), key) for key in AUTO_KEYS}
    chosen = (near.provenance.get("tracker_rule") or {}) if near is not None else {}
    if chosen.get("verdict") is None and check is not None:
        rule = {key: str(check.rule.get(key) or default) for key, default in defaults.items()}
        log.info("tracker rule=auto: %s, the rule of the tracker check beside the pipeline", rule)
        return rule
    rule = {key: str(chosen.get(key) or default) for key, default in defaults.items()}
    if chosen.get("verdict") is not None:
        log.info(
            "tracker rule=auto: %s, chosen on the near-nominal FDI's life split (%s)",
            rule,
            near.provenance["life_split"],
        )
        figures = (chosen.get("rules") or {}).get(f"{rule['verdict']}/{rule['faulty_at']}") or {}
        early = figures.get("eol_flagged_early")
        if announce and early is not None and early > EARLY_WARNING:  # else the tracker check says it
            log.warning(
                "tracker rule=auto: the rule chosen flagged %.0f %% of the ends of life on that split early (flagging "
                "late or never weighs more); expect RULs of 0 well before the end of life. Every rule's figures: %s",
                100 * early,
                chosen["rules"],
            )
    return rule


def track(cfg: DictConfig) -> tuple[dict[str, Any], dict[str, Any]]:
    """Track every actuator of ``cfg.index`` with the pipeline ``cfg.pipeline``; returns (metrics, objects)."""
    torch.set_num_threads(common.integer(cfg.threads, "threads", 1))
    model_path = Path(cfg.pipeline)
    loaded = load_pipeline(model_path)  # checks the file; phm-predict's reader and diagnosis take it
    if not isinstance(loaded, TorchScriptPipeline):
        raise ValueError(
            f"pipeline: {str(model_path)!r} is a {loaded.format!r} file; phm-track needs the "
            f"TorchScript pipeline (its classifier and propagators drive the filter's RUL)"
        )
    metadata = loaded.metadata
    prov, command = _pipeline_command(cfg, metadata, model_path)
    for line in quality_warnings(held_out(metadata)):  # the verdicts the end-of-life rule reads
        log.warning("%s: %s", model_path, line)
    model = loaded.module
    response = companion("response", cfg.response, model_path, model)
    near = companion("near_nominal", cfg.near_nominal, model_path, model)
    check = companion("tracker_check", cfg.tracker_check, model_path, model)
    settings = _settings(cfg, near, announce=check is None, check=check)
    for line in check.warnings({key: getattr(settings, key) for key in AUTO_KEYS}) if check else []:
        log.warning("%s: %s", model_path, line)
    for kind, found in (("response", response), ("near_nominal", near)):
        if found is None and str(cfg[kind]) == "auto":
            log.warning(missing_message(kind, model_path))
    tracker, described = build_tracker(model, metadata, common.plain(cfg.damage), settings, str(model_path), response)
    index = read_index(cfg.index)
    contract = contract_for(model, metadata, command)
    resample = bool(cfg.resample)
    tolerance = tolerance_seconds(cfg.timing_tolerance, "timing_tolerance")
    setting = timing_spread.alignment_setting(cfg.timing_align)
    align = {"on": setting is True}  # auto: decided on the fleet check's first inspections, read unaligned
    bench_nominal, probe = _bench_nominal(cfg, loaded)  # phm-predict's baseline: the bench's healthy record(s)
    bench = None if bench_nominal is None else check_bench(loaded, bench_nominal)
    if bench_nominal is None and loaded.can_rebase:
        log.warning(
            "no baseline: the inspections are read as records of the training model; a bench differing from it by "
            "a few kelvin of winding temperature halves the RUL's coverage (docs/prognostics.md, 'A bench that "
            "differs'); give baseline=<a healthy record of this bench>"
        )
    if bench is not None and not bench.ok:
        log.warning("%s; every inspection is out of distribution (reason 'bench')", bench.message())

    first_inspections: dict[tuple[str, int], dict[str, Any]] = {}  # the fleet check's, read once
    first_currents: list[torch.Tensor] = []  # their currents as diagnose reads them (aligned, sign restored)

    def diagnose_rows(rows: list, keep: list | None = None) -> list[dict[str, Any]]:
        out = []
        for row in rows:
            found = first_inspections.pop((row.actuator, row.line), None)
            if found is None:
                current, m = _read(str(row.path), loaded, resample)
                record = _record(m, current)
                found = inspect_record(
                    loaded, record, contract, bench_nominal, bench, near, probe, tolerance, align["on"]
                )
                if keep is not None:  # the record as the pipeline read it (the same corrections, made again)
                    keep.append(prepare_record(record, contract.command, contract.nominal)[0].current.float())
                # the messages say what was corrected as well as what was refused: "not fused" only for the latter
                tail = "; the inspection is out of distribution (not fused)" if found["out_of_distribution"] else ""
                for message in found["messages"]:
                    log.warning("%s: %s%s", row.path, message, tail)
            out.append(found)
        return out

    def diagnose_first(rows: list) -> list[dict[str, Any]]:
        found = diagnose_rows(rows, first_currents)
        first_inspections.update(((row.actuator, row.line), d) for row, d in zip(rows, found))
        return found

    fleet = _fleet_check(cfg, model, index, diagnose_first)
    if fleet["checked"] and bench_nominal is None and first_currents:
        fleet = probe_in_fleet(fleet, first_currents, loaded.nominal_record if loaded.can_rebase else None)
    first_currents.clear()
    _log_fleet_check(cfg, fleet)
    threshold = timing_spread.fleet_threshold(
        None if check is None else check.timing_share_off
    )  # None: timing not judged
    if timing_spread.decide_alignment(setting, first_inspections.values(), threshold)[0] and not align["on"]:
        align["on"] = True  # timing_align=auto: the first inspections' timing is off; read every one again, aligned
        first_inspections.clear()
        log.warning("timing_align=auto: the first inspections' timing scatters; each is read moved back by its shift")
    if fleet["offset"] and cfg.fleet_check.action == "refuse":
        read = diagnose_rows

        def diagnose_rows(rows: list) -> list[dict[str, Any]]:  # every inspection refused: nothing is fused
            return [refused(d) for d in read(rows)]

    out_dir = Path(cfg.out_dir)
    if cfg.response_out is not None and cfg.truth is None:
        raise ValueError(
            f"response_out={cfg.response_out}: fitting a response needs truth= (a life split's truth.json)"
        )
    run_key = {
        "pipeline_sha256": _sha256(model_path),
        "settings": vars(settings),
        **described,
        "baseline": None if bench_nominal is None else hashlib.sha256(bench_nominal.numpy().tobytes()).hexdigest(),
        "fleet_offset": fleet["offset"] and cfg.fleet_check.action == "refuse",
        "probe": None if probe is None else probe.as_dict(),  # a baseline's calibration (phm-predict's)
        "timing": {"tolerance_s": tolerance, "align": setting},  # how each inspection was read
        # the companions' whole content: a resumed run with another response or near-nominal file is recomputed
        "near_nominal": None if near is None else _tensors_sha256(near.state_dict()),
        "response": None if response is None else fingerprint(response.to_json()),
    }
    actuators = track_fleet(
        index,
        tracker,
        model,
        diagnose_rows,
        out_dir / "state" if cfg.resume else None,
        run_key,
        common.integer(cfg.chunk_size, "chunk_size", 1),
    )
    result = {
        "pipeline": str(model_path),
        "actuator": prov["actuator"],
        "command": prov["command"],
        "tracker": {
            "settings": vars(settings),
            **described,
            "near_nominal": None
            if near is None
            else {"gate": near.gate, "noise_max": near.noise_max, **near.provenance},
        },
        "actuators": actuators,
        "fleet": fleet_list(actuators),
    }
    common.write_json(out_dir / "track.json", result)
    common.write_json(out_dir / "fleet.json", {k: result[k] for k in ("pipeline", "actuator", "command", "fleet")})
    inspections = [i for a in actuators.values() for i in a["inspections"]]
    spread = timing_spread.timing_spread(inspections)
    if (line := timing_spread.spread_message(spread, threshold, align["on"])) is not None:
        log.warning(line)
    metrics: dict[str, Any] = {
        "actuators": len(actuators),
        "inspections": len(inspections),
        "fused": sum(i["fused"] for i in inspections),
        "out_of_distribution": sum(i["out_of_distribution"] for i in inspections),
        "baseline": bench_nominal is not None,
        "bench_check": None if bench is None else bench.as_dict(),
        "probe_calibration": None if probe is None else probe.as_dict(),
        "fleet_check": fleet,
        "damage_source": described["damage_source"],
        "tracker_check": None if check is None else check.to_json(),
        "timing": None if spread is None else {**spread, "aligned": align["on"], "threshold": threshold},
        "out_dir": str(out_dir),
        "actuator": provenance.describe(prov["actuator"]),
        "command": provenance.describe(prov["command"]),
    }
    objects: dict[str, Any] = {"track": result}
    if cfg.truth is not None:
        from ..prognostics.life_metrics import evaluate_life
        from ..prognostics.life_plots import plot_life

        truth_path = Path(cfg.truth)
        if not truth_path.is_file():
            raise ValueError(f"truth: no such file {str(truth_path)!r}")
        truth = json.loads(truth_path.read_text())
        metrics["same_assessment"] = same_labels(metadata.get("assessment"), truth.get("assessment"))
        if metrics["same_assessment"] is False:
            log.warning(
                "truth %s was labelled by another assessment function than the pipeline's classifiers learned: "
                "their health boundaries differ, and the end-of-life timing is judged against the truth's",
                truth_path,
            )
        elif metrics["same_assessment"] is None:
            log.info("%s or %s records no assessment config: not compared", model_path, truth_path)
        scores = evaluate_life(result, truth)
        scores["limit"] = _limit(cfg, model, metadata, settings, model_path, truth, prov["actuator"])
        common.write_json(out_dir / "metrics.json", {**scores, "tracking": metrics})
        objects["life_metrics"] = scores
        objects["figures"] = plot_life(result, truth, out_dir)
        metrics["tracker"], metrics["snapshot"] = scores.get("tracker"), scores.get("snapshot")
        metrics["limit"] = scores["limit"]
        if cfg.response_out is not None:
            k_true, k_hat = pairs_from_track(result, truth)
            fitted = fit_response(
                k_true,
                k_hat,
                pipeline={
                    "source": str(model_path),
                    "sha256": run_key["pipeline_sha256"],
                    "probe_k_hat": probe_k_hat(model),
                    "actuator": provenance.describe(prov["actuator"]),
                    "command": provenance.describe(prov["command"]),
                    "life_split": str(truth_path),
                },
            )
            fitted.save(cfg.response_out)
            log.info(
                "FDI response fitted on %d inspections (moves %s): %s", len(k_true), fitted.corrected, cfg.response_out
            )
            metrics["fdi_response_out"] = str(cfg.response_out)
    return metrics, objects


def _limit(
    cfg: DictConfig,
    model: Any,
    metadata: dict[str, Any],
    settings: TrackerSettings,
    path: Path,
    truth: dict[str, Any],
    actuator: dict[str, Any] | None,
) -> dict[str, Any] | None:
    """What the histories leave to know (:mod:`~phm_torch.tracking.information_limit`): a fresh tracker of the same
    settings fed the truth's k within ``cfg.limit_error_std``, scored as this run; None when that is null, the
    truth has no ``k_true`` at every inspection, or it records another actuator than the pipeline's ``actuator``
    (each logged: the pipeline's classifier says nothing of another actuator's true k)."""
    error_std = cfg.limit_error_std
    if error_std is None:
        return None
    other = truth.get("actuator")
    if isinstance(other, dict) and actuator and other.get("sha256") and other["sha256"] != actuator.get("sha256"):
        log.warning(
            "truth is of the actuator %s, the pipeline of %s: the tracking limit (the true k tracked) is not computed, "
            "and the run's scores judge this pipeline on another actuator's histories",
            provenance.describe(other),
            provenance.describe(actuator),
        )
        return None
    if not all("k_true" in row for a in truth["actuators"].values() for row in a.get("inspections", [])):
        log.info("truth has no k_true at every inspection: the tracking limit (the true k tracked) is not computed")
        return None
    tracker, _ = build_tracker(model, metadata, common.plain(cfg.damage), settings, str(path))
    found = information_limit(track_truth(tracker, truth, float(error_std), settings.seed), truth)
    t, c = found["tracking"], found["classifier_on_true_k"]
    log.info(
        "with the true k (+-%g), the same filter reaches coverage %s, alpha-lambda %s, prognostic horizon %s, end of "
        "life within one inspection %s; the health classifier on the true k flags %s of the ends of life within one "
        "inspection (docs/prognostics.md, 'What the histories leave to know')",
        float(error_std),
        *(_rounded(v) for v in (t["coverage_5_95"], t["alpha_lambda"], t["prognostic_horizon"])),
        _rounded(t["eol_flagged_within_one_inspection"]),
        _rounded(c["eol_flagged_within_one_inspection"]),
    )
    return found


def _rounded(value: float | None) -> str:
    return "-" if value is None else f"{value:.3g}"


def _fleet_check(cfg: DictConfig, model: Any, index: dict[str, list], diagnose_rows: Any) -> dict[str, Any]:
    """The fleet check (:mod:`~phm_torch.tracking.fleet_check`) of each actuator's first inspection."""
    settings = FleetCheckSettings(**common.plain(cfg.fleet_check))
    return check_fleet(diagnose_rows([rows[0] for rows in index.values()]), model.nominal.tolist(), settings)


def _log_fleet_check(cfg: DictConfig, fleet: dict[str, Any]) -> None:
    """What the fleet check found, and what is done about it, logged."""
    settings = FleetCheckSettings(**common.plain(cfg.fleet_check))
    if fleet["offset"]:
        action = "every inspection is out of distribution (reason 'fleet_offset'), nothing is fused"
        log.warning(
            "fleet check: %s; %s", fleet["message"], action if settings.action == "refuse" else "tracked as read"
        )
    elif not fleet["checked"]:
        log.info(
            "fleet check: %d usable first inspections, fewer than %d: not checked",
            fleet["n_actuators"],
            settings.min_actuators,
        )


@hydra.main(config_path=common.CONFIG_PATH, config_name="track", version_base="1.3")
@common.report_errors("phm-track")
def main(cfg: DictConfig) -> None:
    metrics, _ = track(cfg)
    print(json.dumps(metrics, indent=2), flush=True)


if __name__ == "__main__":
    main()
