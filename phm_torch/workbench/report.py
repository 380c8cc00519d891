"""The workbench report: ``report.json`` (numbers), PNG figures and ``report.html`` (figures embedded as
base64), all written atomically.

``report.json`` keys: ``nrmse`` / ``fit_percent`` / ``noise_floor`` ({channel: value, "total": value}, NRMSE
as fractions) of the calibrated configured model; ``worst_windows`` [{record, t_start, t_end, nrmse}];
``candidates`` [{effect, score, dof, p_value, significant, nrmse_after_refit, delta_bic, evidence...}] best
first; ``fitted`` {parameter: [value, std]}; ``before_after`` rows; ``closure``; ``diagnostics``; ``timing``;
``bench_lines`` {record: [{frequency, amplitude, phase, share}]}: lines of the measured current the model does not
make, removed before calibrating (:mod:`phm_torch.workbench.bench_lines`).
"""

from __future__ import annotations

import hashlib
import json
import math
import os
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from ..effects import EFFECTS
from ..io.atomic import atomic_open
from ..provenance import actuator_record
from ..report.workbench import html_page
from . import plots
from .calibrate import Calibration
from .candidates import Candidate
from .diagnostics import error_metrics
from .result import WorkbenchResult

TOP_HARMONICS = 5


def calibration_metrics(cal: Calibration, sigma: list[dict[str, float]]) -> dict:
    """NRMSE / fit % / noise floor of a calibrated model (see :func:`error_metrics`)."""
    measured = [{c: r.measured[c].numpy() for c in cal.evaluator.channels} for r in cal.evaluator.records]
    return error_metrics(cal.errors(), measured, sigma)


def _clean(obj: Any) -> Any:
    """JSON-safe copy: numpy -> lists/floats, NaN/inf -> None."""
    if isinstance(obj, Mapping):
        return {str(k): _clean(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_clean(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return _clean(obj.tolist())
    if isinstance(obj, (np.floating, float)):
        return plots.finite(float(obj))
    if isinstance(obj, (np.integer,)):
        return int(obj)
    if isinstance(obj, np.bool_):
        return bool(obj)
    return obj


def _fitted(cal: Calibration) -> dict[str, list[float]]:
    return {k: [v, s] for k, (v, s) in cal.fitted().items()}


def _tests(diag: dict) -> dict:
    return {
        "whiteness": {
            c: {k: v[k] for k in ("p_value", "white", "q", "dof", "outside_fraction")}
            for c, v in diag["whiteness"].items()
        },
        "cross_correlation": {
            c: {k: v[k] for k in ("p_value", "uncorrelated", "statistic", "outside_fraction")}
            for c, v in diag["cross_correlation"].items()
        },
    }


def label(effect: str, values: Mapping[str, float]) -> str:
    """An effect's name, with its order when it has one (``torque_ripple, order 17``)."""
    cls = EFFECTS.get(effect)
    if cls is not None and "order" in cls.PARAMS and "order" in values:
        return f"{effect}, order {values['order']:g}"
    return effect


def _file_record(path: Path) -> dict:
    """{"path", "sha256"} of a measurement file (sha256 None when the file is gone)."""
    digest = hashlib.sha256(path.read_bytes()).hexdigest() if path.is_file() else None
    return {"path": str(path), "sha256": digest}


def _candidate(c: Candidate, base: dict, noise: list[dict[str, float]]) -> dict:
    row: dict[str, Any] = {
        "effect": c.effect,
        "label": label(c.effect, c.start),
        "score": c.score,
        "dof": c.dof,
        "p_value": c.p_value,
        "log10_p_value": c.log10_p,
        "significant": c.significant,
        "nrmse_after_refit": None,
        "nrmse_after_refit_channels": None,
        "delta_nrmse": None,
        "delta_bic": c.delta_bic,
        "explained_fraction": c.explained_fraction,
        "aliased_with": c.aliased_with,
        "evidence": c.evidence,
        "fitted": None,
    }
    if c.refit is not None:
        m = calibration_metrics(c.refit, noise)
        row.update(
            nrmse_after_refit=m["nrmse"]["total"],
            nrmse_after_refit_channels=m["nrmse"],
            delta_nrmse=m["nrmse"]["total"] - base["nrmse"]["total"],
            fitted={k: v for k, v in _fitted(c.refit).items() if k.startswith(f"{c.effect}.")},
        )
    return row


def report_dict(res: WorkbenchResult) -> dict:
    """Every number of the report, JSON-able (NaN as null)."""
    model, noise = res.model, res.noise
    m0 = res.metrics[model.label]
    d0 = res.diagnostics[model.label]
    k = max(1, len(res.candidates))
    rows = []
    for cal in res.before_after:
        m = res.metrics[cal.label]
        t = _tests(res.diagnostics[cal.label])
        rows.append(
            {
                "model": cal.label,
                "effects": sorted(cal.space.effects),
                "nrmse": m["nrmse"],
                "fit_percent": m["fit_percent"],
                "chi2": cal.chi2,
                "bic": cal.bic,
                "parameters": cal.space.n,
                "whiteness_p": {c: v["p_value"] for c, v in t["whiteness"].items()},
                "white": all(v["white"] for v in t["whiteness"].values()),
                "fitted": {kk: v for kk, v in _fitted(cal).items() if not kk.startswith("closure.")},
            }
        )
    harm = {
        c: [
            {
                "order": int(i + 1),
                "electrical_order": (i + 1) / res.model.space.params.pole_pairs,
                "amplitude": float(a[i]),
            }
            for i in np.argsort(a)[::-1][:TOP_HARMONICS]
        ]
        for c, a in d0["harmonics"].items()
    }
    closure = None
    if res.closure is not None:
        cm = res.metrics[res.closure.calibration.label]
        gain = (res.final.chi2 - res.closure.calibration.chi2) / res.final.chi2
        closure = {
            "equation": res.settings.closure.equation,
            "harmonics": list(res.closure.harmonics),
            "inputs": res.closure.attribution.shares,
            "output_rms": res.closure.attribution.output_rms,
            "unit": res.closure.attribution.unit,
            "nrmse": cm["nrmse"],
            "lead": next(iter(res.closure.attribution.shares), None),
            "explained_fraction": gain,
            "explains": gain >= res.settings.score.min_gain,
        }
    params = model.space.params
    out = {
        "actuator": actuator_record(res.actuator, params),
        "measurements": [str(r.path) if r.path else r.name for r in res.records],
        "measurement_files": [_file_record(Path(r.path)) for r in res.records if r.path],
        "records": [{"name": r.name, "samples": len(r), "duration_s": r.duration, "t0": r.t0} for r in res.records],
        "fidelity": res.fidelity,
        "channels": list(model.evaluator.channels),
        "model": {"label": model.label, "effects": model.space.effect_values(model.x)},
        "nrmse": m0["nrmse"],
        "fit_percent": m0["fit_percent"],
        "noise_floor": m0["noise_floor"],
        "noise_std": m0["noise_std"],
        "worst_windows": d0["worst_windows"],
        "tests": _tests(d0),
        "harmonics": harm,
        "orders": res.orders,
        "candidates": [_candidate(c, m0, noise) for c in res.candidates],
        "significance_level": res.settings.score.alpha / k,
        "min_gain": res.settings.score.min_gain,
        "added": res.added,
        "added_labels": [label(n, res.final.space.effects.get(n, {})) for n in res.added],
        "rounds": [
            {
                "model": r.model.label,
                "added": r.added,
                "ranking": [c.effect for c in r.candidates],
                "significant": [c.effect for c in r.candidates if c.significant],
            }
            for r in res.rounds
        ],
        "fitted": _fitted(model),
        "final": {
            "label": res.final.label,
            "effects": res.final.space.effect_values(res.final.x),
            "nrmse": res.metrics[res.final.label]["nrmse"] if res.final.label in res.metrics else None,
            "fitted": _fitted(res.final),
        },
        "before_after": rows,
        "closure": closure,
        "fidelity_gap": res.fidelity_gap,
        "bench_lines": res.bench_lines,
        "retrain": generate_overrides(res.final.space.effect_values(res.final.x)) if res.added else None,
        "timing": res.timing,
    }
    return _clean(out)


def generate_overrides(effects: dict[str, dict[str, float]]) -> str:
    """The phm-generate overrides that put ``effects`` {name: {param: value}} (the final model's, fitted)
    into training records: the surrogates then learn the physics the measurement showed."""

    def value(v: float) -> str:
        return f"{v:.6g}"

    return " ".join(
        "'+dataset.effects." + name + "={" + ", ".join(f"{k}: {value(v)}" for k, v in params.items()) + "}'"
        for name, params in effects.items()
    )


def figures(res: WorkbenchResult, report: dict) -> dict[str, bytes]:
    """The report's PNG figures {file name: bytes}."""
    shown = res.before_after
    chans = list(res.model.evaluator.channels)
    rec = res.records[0]
    sigma0 = {c: res.noise[0][c] for c in chans}
    p = res.model.space.params
    figs = {
        "overlay.png": plots.overlay(
            rec.time.numpy(),
            {c: rec.measured[c].numpy() for c in chans},
            {cal.label: {c: cal.simulated[0][c].numpy() for c in chans} for cal in shown},
            sigma0,
            [w for w in report["worst_windows"] if w["record"] == rec.name],
            f"{rec.name}: measured vs simulated ({res.fidelity.upper()} model)",
        ),
        "residual_maps.png": plots.maps({c.label: res.diagnostics[c.label]["profiles"] for c in shown}, chans),
        "harmonics.png": plots.harmonic_bars(
            {c.label: res.diagnostics[c.label]["harmonics"] for c in shown},
            chans,
            p.pole_pairs,
            res.orders.get("actuator", {}).get("cogging", p.stator_slots),
        ),
        "spectrum.png": plots.spectra(
            {c.label: res.diagnostics[c.label]["spectrum"] for c in shown}, sigma0, p.sample_rate
        ),
        "correlations.png": plots.correlations(
            {c.label: res.diagnostics[c.label]["whiteness"] for c in shown},
            {c.label: res.diagnostics[c.label]["cross_correlation"] for c in shown},
            p.sample_rate,
        ),
        "before_after.png": plots.before_after(report["before_after"], report["noise_floor"]),
    }
    if report["candidates"]:
        figs["candidates.png"] = plots.candidate_bars(report["candidates"], math.log10(report["significance_level"]))
    if res.closure is not None:
        figs["closure.png"] = plots.attribution(res.closure.attribution.shares, "Neural closure: what it depends on")
    return figs


def write_report(res: WorkbenchResult, out_dir: str | os.PathLike, plot: bool = True) -> dict[str, Path]:
    """Write ``report.json`` (and, with ``plot``, the PNGs and ``report.html``) into ``out_dir``, atomically."""
    out = Path(out_dir)
    report = report_dict(res)
    paths = {}
    if plot:
        figs = figures(res, report)
        for name, data in figs.items():
            with atomic_open(out / name, "wb") as fh:
                fh.write(data)
            paths[name] = out / name
        with atomic_open(out / "report.html", "w", encoding="utf-8") as fh:
            fh.write(html_page(report, figs))
        paths["report.html"] = out / "report.html"
    report["files"] = {k: str(v) for k, v in paths.items()}
    with atomic_open(out / "report.json", "w") as fh:
        json.dump(report, fh, indent=2)
        fh.write("\n")
    paths["report.json"] = out / "report.json"
    return paths
