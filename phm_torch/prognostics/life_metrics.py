"""Prognostic metrics of a life track (Saxena et al. 2010, named as NASA ProgPy names them).

An actuator's *profile* is its inspections before the true end of life (EOL), each with the true RUL and
a predicted RUL 5/50/95 % [h]. A censored bound (``null`` in track.json: beyond the pipeline's horizon) is
+inf here. Choices where Saxena / ProgPy leave one (docs/prognostics.md, "Life tracking metrics"):

* the prediction tested against the alpha bounds is the p50 (the track keeps three quantiles, not the
  distribution, so ProgPy's "mass in bounds >= beta" cannot be computed without assuming a shape);
* the prognostic horizon is *sustained*: the first inspection from which every later p50 stays within
  RUL_true +- horizon_alpha x life (ProgPy takes the first entry into the bounds; a p50 that wanders in
  and out again should not earn a horizon);
* fleet figures of per-actuator values are medians (a censored p50 gives RA = -inf; a mean would be -inf);
* JSON: every infinite value (a censored band's width, a never-flagged EOL) is written as ``null``; each
  fleet figure comes with the count it was computed over.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

log = logging.getLogger(__name__)

HOURS_TOLERANCE = 1e-6  # [h] a track's hours must equal the truth's within this
METHODS = {"tracker": ("rul_hours", "rul_censored"), "snapshot": ("snapshot_rul_hours", "snapshot_rul_censored")}


# ---------------------------------------------------------------- metrics on arrays (one actuator's profile)


def lambda_index(hours: np.ndarray, t_start: float, eol: float, lam: float) -> int | None:
    """Index of the first inspection at or after t_lambda = t_start + lam (eol - t_start) and before eol.

    Args: hours (n,) increasing [h]; t_start, eol [h]; lam in [0, 1]. Returns None when there is none.
    """
    t_lam = t_start + lam * (eol - t_start)
    idx = np.flatnonzero((np.asarray(hours) >= t_lam - HOURS_TOLERANCE) & (np.asarray(hours) < eol))
    return int(idx[0]) if idx.size else None


def in_alpha_bounds(rul_true: np.ndarray, rul_pred: np.ndarray, alpha: float) -> np.ndarray:
    """(n,) bool: rul_pred within (1 - alpha, 1 + alpha) x rul_true (the alpha-lambda cone), rul_true > 0 [h]."""
    t, p = np.asarray(rul_true, float), np.asarray(rul_pred, float)
    return (p >= (1 - alpha) * t) & (p <= (1 + alpha) * t)


def alpha_lambda(
    hours: np.ndarray,
    rul_true: np.ndarray,
    rul_p50: np.ndarray,
    t_start: float,
    eol: float,
    alpha: float = 0.2,
    lam: float = 0.5,
) -> bool | None:
    """Alpha-lambda accuracy of one actuator: is the p50 at the lambda inspection inside the alpha cone?

    Args: hours, rul_true, rul_p50 (n,) [h] of the inspections before eol; t_start, eol [h].
    Returns None when no inspection lies in [t_lambda, eol).
    """
    i = lambda_index(hours, t_start, eol, lam)
    return None if i is None else bool(in_alpha_bounds(rul_true[i : i + 1], rul_p50[i : i + 1], alpha)[0])


def relative_accuracy(rul_true: np.ndarray, rul_pred: np.ndarray) -> np.ndarray:
    """RA = 1 - |RUL_true - RUL_pred| / RUL_true, elementwise (n,); 1 is perfect, -inf for a censored p50."""
    t, p = np.asarray(rul_true, float), np.asarray(rul_pred, float)
    with np.errstate(invalid="ignore"):
        return np.where(np.isinf(p), -np.inf, 1.0 - np.abs(t - p) / t)


def prognostic_horizon(
    hours: np.ndarray, rul_true: np.ndarray, rul_p50: np.ndarray, eol: float, life: float, alpha: float = 0.1
) -> float:
    """Prognostic horizon [h]: eol minus the first inspection from which every later p50 stays within
    rul_true +- alpha x life (Saxena's constant-width bounds). 0 when the last inspection is outside.

    Args: hours, rul_true, rul_p50 (n,) [h] of the inspections before eol, increasing; eol, life [h].
    """
    t, p = np.asarray(rul_true, float), np.asarray(rul_p50, float)
    inside = np.abs(p - t) <= alpha * life
    outside = np.flatnonzero(~inside)
    first = 0 if outside.size == 0 else int(outside[-1]) + 1
    return 0.0 if first >= len(t) else float(eol - hours[first])


def covered(rul_true: np.ndarray, p5: np.ndarray, p95: np.ndarray) -> np.ndarray:
    """(n,) bool: p5 <= rul_true <= p95 (a censored p95 is +inf, so covers every larger truth)."""
    t = np.asarray(rul_true, float)
    return (np.asarray(p5, float) <= t) & (t <= np.asarray(p95, float))


def relative_band_width(rul_true: np.ndarray, p5: np.ndarray, p95: np.ndarray) -> np.ndarray:
    """(p95 - p5) / rul_true, (n,); +inf when p95 is censored (the band has no finite width)."""
    lo, hi = np.asarray(p5, float), np.asarray(p95, float)
    with np.errstate(invalid="ignore"):
        width = np.where(np.isinf(hi), np.inf, hi - lo)
    return width / np.asarray(rul_true, float)


def eol_detection_delay(hours: np.ndarray, flagged: np.ndarray, eol: float) -> float:
    """Hours from the true eol to the first flagged inspection (negative: flagged before eol); +inf if never.

    Args: hours (n,) [h] of every (in-distribution) inspection, increasing; flagged (n,) bool.
    """
    idx = np.flatnonzero(np.asarray(flagged, bool))
    return float(hours[idx[0]] - eol) if idx.size else math.inf


def eol_intervals_off(delay: float, every: float, hours: np.ndarray, eol: float) -> dict[str, float]:
    """How far beyond one inspection interval the end of life was flagged, in intervals: ``eol_intervals_early``
    max(0, -delay / every - 1), ``eol_intervals_late`` max(0, delay / every - 1); a flag within one interval costs
    nothing. A life never flagged counts as flagged one interval after its last inspection (``hours`` (n,) [h]), a
    lower bound."""
    if math.isinf(delay):
        delay = (float(hours[-1]) if len(hours) else eol) + every - eol
    return {
        "eol_intervals_early": max(0.0, -delay / every - 1.0),
        "eol_intervals_late": max(0.0, delay / every - 1.0),
    }


# ---------------------------------------------------------------- reading track.json / truth.json


def _quantiles(inspection: Mapping[str, Any], key: str) -> tuple[float, float, float]:
    """(p5, p50, p95) [h]; a null bound (or a null dict: all censored) is +inf."""
    q = inspection.get(key)
    if q is None:
        return (math.inf,) * 3
    return tuple(math.inf if q.get(n) is None else float(q[n]) for n in ("p5", "p50", "p95"))


def _finite_or_none(x: float | None) -> float | None:
    """x as a JSON number (ints stay ints), None for None and +-inf."""
    if x is None or not math.isfinite(x):
        return None
    return x if isinstance(x, int) and not isinstance(x, bool) else float(x)


def _median(values: Sequence[float]) -> float | None:
    return float(np.median(values)) if len(values) else None


def inspection_spacing(truth: Mapping[str, Any]) -> float | None:
    """Median hours between consecutive inspections over every actuator of ``truth`` (None: no actuator has two)."""
    gaps = [np.diff([float(i["hours"]) for i in g["inspections"]]) for g in truth["actuators"].values()]
    gaps = np.concatenate(gaps) if gaps else np.zeros(0)
    return float(np.median(gaps)) if gaps.size else None


def check_inputs(track: Mapping[str, Any], truth: Mapping[str, Any]) -> None:
    """ValueError naming the actuator and the value when track and truth do not describe the same
    actuators and inspection hours."""
    t_ids, g_ids = track.get("actuators"), truth.get("actuators")
    if not isinstance(t_ids, Mapping) or not isinstance(g_ids, Mapping):
        raise ValueError("evaluate_life: track and truth need an 'actuators' mapping")
    for a in t_ids:
        if a not in g_ids:
            raise ValueError(f"evaluate_life: actuator {a!r} is in the track but not in the truth")
    for a in g_ids:
        if a not in t_ids:
            raise ValueError(f"evaluate_life: actuator {a!r} is in the truth but not in the track")
    for a, g in g_ids.items():
        th = [float(i["hours"]) for i in t_ids[a]["inspections"]]
        gh = [float(i["hours"]) for i in g["inspections"]]
        for j, (x, y) in enumerate(zip(th, gh)):
            if abs(x - y) > HOURS_TOLERANCE:
                raise ValueError(f"evaluate_life: actuator {a!r} inspection {j}: track hours {x} != truth hours {y}")
        if len(th) != len(gh):
            extra = th[len(gh)] if len(th) > len(gh) else gh[len(th)]
            raise ValueError(
                f"evaluate_life: actuator {a!r} has {len(th)} inspections in the track and {len(gh)} "
                f"in the truth (first unmatched hours {extra})"
            )
        eol = g.get("eol_hours")
        if eol is not None and not math.isfinite(float(eol)):
            raise ValueError(f"evaluate_life: actuator {a!r} eol_hours = {eol} is not finite")


def _flags(inspections: Sequence[Mapping[str, Any]], method: str) -> np.ndarray:
    """(n,) bool: the method says 'end of life' here: a faulty verdict or a p50 of 0."""
    key, _ = METHODS[method]
    verdict = "healthy" if method == "tracker" else "snapshot_healthy"
    return np.array([(i.get(verdict) is False) or _quantiles(i, key)[1] <= 0.0 for i in inspections], bool)


def _actuator(
    track_a: Mapping[str, Any], truth_a: Mapping[str, Any], every: float, alpha: float, lam: float, horizon_alpha: float
) -> dict[str, Any]:
    """Per-actuator metrics for both methods, plus the raw arrays the fleet figures pool."""
    insp = track_a["inspections"]
    hours = np.array([float(i["hours"]) for i in insp])
    ood = np.array([bool(i.get("out_of_distribution", False)) for i in insp])
    eol = truth_a.get("eol_hours")
    t_start = float(truth_a["inspections"][0]["hours"]) if truth_a["inspections"] else 0.0
    out: dict[str, Any] = {
        "eol_hours": eol,
        "rate_scale": truth_a.get("rate_scale"),
        "n_inspections": len(insp),
        "n_out_of_distribution": int(ood.sum()),
    }
    pooled: dict[str, Any] = {}
    if eol is None:  # a run that never reached its end of life: no truth to score against
        out["life_hours"] = None
        return {"values": out, "pooled": pooled}
    eol = float(eol)
    life = eol - t_start
    out["life_hours"] = life
    valid = (~ood) & (hours < eol)
    h, rul_true = hours[valid], eol - hours[valid]
    second = h >= t_start + 0.5 * life
    for method, (key, _) in METHODS.items():
        q = np.array([_quantiles(i, key) for i in insp]).reshape(-1, 3)
        p5, p50, p95 = q[valid, 0], q[valid, 1], q[valid, 2]
        i_lam = lambda_index(h, t_start, eol, lam)
        ra = None if i_lam is None else float(relative_accuracy(rul_true[i_lam : i_lam + 1], p50[i_lam : i_lam + 1])[0])
        ph = prognostic_horizon(h, rul_true, p50, eol, life, horizon_alpha) if len(h) else 0.0
        cov = covered(rul_true, p5, p95)
        width = relative_band_width(rul_true[second], p5[second], p95[second])
        delay = eol_detection_delay(hours[~ood], _flags(insp, method)[~ood], eol)
        verdicts = [i.get("healthy" if method == "tracker" else "snapshot_healthy") for i in insp]
        violations = (
            None
            if all(v is None for v in verdicts)
            else int(sum(v is False and _quantiles(i, key)[1] > 0.0 for v, i in zip(verdicts, insp)))
        )
        out[method] = {
            "alpha_lambda": alpha_lambda(h, rul_true, p50, t_start, eol, alpha, lam),
            "relative_accuracy": _finite_or_none(ra),
            "prognostic_horizon_hours": ph,
            "prognostic_horizon_fraction": ph / life if life > 0 else None,
            "coverage_5_95": float(cov.mean()) if cov.size else None,
            "median_relative_band_width_second_half": _finite_or_none(_median(width)) if width.size else None,
            "eol_detection_delay_hours": _finite_or_none(delay),
            "eol_flagged_within_one_inspection": bool(abs(delay) <= every + HOURS_TOLERANCE),
            "eol_flagged_early": bool(delay < -every - HOURS_TOLERANCE),
            **eol_intervals_off(delay, every, hours[~ood], eol),
            "positive_p50_when_faulty": violations,
        }
        pooled[method] = {
            "covered": cov,
            "width": width,
            "ra": ra,
            "delay": delay,
            "p50_in_alpha_second_half": in_alpha_bounds(rul_true[second], p50[second], alpha),
        }
    return {"values": out, "pooled": pooled}


def _fleet(per: Mapping[str, Mapping[str, Any]], method: str) -> dict[str, Any]:
    """Fleet figures of one method from the per-actuator values and pooled inspections."""
    vals = [p["values"][method] for p in per.values() if method in p["values"]]
    pools = [p["pooled"][method] for p in per.values() if method in p["pooled"]]
    al = [v["alpha_lambda"] for v in vals if v["alpha_lambda"] is not None]
    ras = [p["ra"] for p in pools if p["ra"] is not None]
    phf = [v["prognostic_horizon_fraction"] for v in vals if v["prognostic_horizon_fraction"] is not None]
    cov = np.concatenate([p["covered"] for p in pools]) if pools else np.zeros(0, bool)
    width = np.concatenate([p["width"] for p in pools]) if pools else np.zeros(0)
    in_a = np.concatenate([p["p50_in_alpha_second_half"] for p in pools]) if pools else np.zeros(0, bool)
    delays = [p["delay"] for p in pools]
    viol = [v["positive_p50_when_faulty"] for v in vals if v["positive_p50_when_faulty"] is not None]
    return {
        "alpha_lambda": float(np.mean(al)) if al else None,
        "alpha_lambda_n": len(al),
        "relative_accuracy": _finite_or_none(_median(ras)),
        "relative_accuracy_n": len(ras),
        "prognostic_horizon": _median(phf),
        "prognostic_horizon_n": len(phf),
        "prognostic_horizon_hours": _median([v["prognostic_horizon_hours"] for v in vals]),
        "coverage_5_95": float(cov.mean()) if cov.size else None,
        "coverage_5_95_n": int(cov.size),
        "median_relative_band_width_second_half": _finite_or_none(_median(width)) if width.size else None,
        "relative_band_width_second_half_n": int(width.size),
        "relative_band_width_second_half_censored": float(np.isinf(width).mean()) if width.size else None,
        "p50_within_alpha_second_half": float(in_a.mean()) if in_a.size else None,
        "eol_detection_delay": _finite_or_none(_median(delays)),
        "eol_flagged_within_one_inspection": (
            float(np.mean([v["eol_flagged_within_one_inspection"] for v in vals])) if vals else None
        ),
        "eol_flagged_early": float(np.mean([v["eol_flagged_early"] for v in vals])) if vals else None,
        "eol_never_flagged": int(sum(math.isinf(d) for d in delays)),
        "eol_intervals_early": float(np.mean([v["eol_intervals_early"] for v in vals])) if vals else None,
        "eol_intervals_late": float(np.mean([v["eol_intervals_late"] for v in vals])) if vals else None,
        "positive_p50_when_faulty": int(sum(viol)) if viol else None,
        "_width_raw": _median(width) if width.size else None,
    }


def _targets(tracker: Mapping[str, Any], snapshot: Mapping[str, Any]) -> dict[str, dict[str, Any]]:
    """Issue 25's deliverable 5: each target with value, target and passed (a missing value fails)."""

    def row(value: float | None, target: float, ok: bool) -> dict[str, Any]:
        return {"value": _finite_or_none(value), "target": target, "passed": bool(value is not None and ok)}

    w, ws = tracker["_width_raw"], snapshot["_width_raw"]
    if w is None or ws is None:
        ratio = None
    elif math.isinf(w) or w == 0:
        ratio = w  # an infinite band is no better than any; a zero band beats every one
    else:
        ratio = w / ws if ws > 0 else math.inf
    al, ph = tracker["alpha_lambda"], tracker["prognostic_horizon"]
    cov, fl = tracker["coverage_5_95"], tracker["eol_flagged_within_one_inspection"]
    viol = tracker["positive_p50_when_faulty"]
    return {
        "coverage_5_95": row(cov, 0.85, cov is not None and cov >= 0.85),
        "median_relative_band_width_second_half": row(w, 1.0, w is not None and w <= 1.0),
        "band_width_ratio_to_snapshot": row(ratio, 0.1, ratio is not None and ratio <= 0.1),
        "alpha_lambda": row(al, 0.7, al is not None and al >= 0.7),
        "prognostic_horizon": row(ph, 0.6, ph is not None and ph >= 0.6),
        "eol_flagged_within_one_inspection": row(fl, 0.9, fl is not None and fl >= 0.9),
        "positive_p50_when_faulty": row(viol, 0, viol == 0),
    }


def evaluate_life(
    track: Mapping[str, Any], truth: Mapping[str, Any], alpha: float = 0.2, lam: float = 0.5, horizon_alpha: float = 0.1
) -> dict[str, Any]:
    """Tracker and snapshot RULs of a life split scored against the truth, side by side.

    Args:
        track: track.json (issue 25's contract): ``actuators[id].inspections[]`` with ``hours``,
            ``rul_hours`` / ``snapshot_rul_hours`` {p5, p50, p95} [h] (null = censored), ``healthy``,
            ``out_of_distribution``.
        truth: truth.json: ``every_hours`` (absent: the inspections' median spacing), ``actuators[id]`` with
            ``eol_hours`` (``rate_scale`` optional), ``inspections[].hours`` (the same hours as the track).
        alpha: half-width of the alpha-lambda cone, a fraction of the true RUL.
        lam: where alpha-lambda and relative accuracy are taken, a fraction of the life.
        horizon_alpha: half-width of the prognostic-horizon bounds, a fraction of the life.

    Returns:
        {"tracker": {...}, "snapshot": {...}, "targets": {...}, "per_actuator": {id: {...}},
         "n_actuators", "n_inspections", "n_out_of_distribution", "n_without_eol", "settings"}.
        Out-of-distribution inspections are excluded from every metric but counted.
    """
    for name, v, ok in (
        ("alpha", alpha, 0 < alpha < 1),
        ("lam", lam, 0 <= lam <= 1),
        ("horizon_alpha", horizon_alpha, 0 < horizon_alpha <= 1),
    ):
        if not ok:
            raise ValueError(f"evaluate_life: {name} = {v!r} is outside its range")
    check_inputs(track, truth)
    every = truth.get("every_hours")
    if every is None:  # a truth written by another tool: the inspections' own spacing
        every = inspection_spacing(truth)
        log.info("truth has no every_hours: the inspections' median spacing, %g h, is the one-inspection window", every)
    if isinstance(every, bool) or not isinstance(every, (int, float)) or not every > 0:
        raise ValueError(f"evaluate_life: truth.every_hours must be > 0, got {every!r}")
    per = {
        a: _actuator(track["actuators"][a], g, float(every), alpha, lam, horizon_alpha)
        for a, g in truth["actuators"].items()
    }
    fleet = {m: _fleet(per, m) for m in METHODS}
    targets = _targets(fleet["tracker"], fleet["snapshot"])
    for m in fleet.values():
        m.pop("_width_raw")
    values = [p["values"] for p in per.values()]
    return {
        **fleet,
        "targets": targets,
        "all_targets_passed": all(t["passed"] for t in targets.values()),
        "per_actuator": {a: p["values"] for a, p in per.items()},
        "n_actuators": len(per),
        "n_inspections": sum(v["n_inspections"] for v in values),
        "n_out_of_distribution": sum(v["n_out_of_distribution"] for v in values),
        "n_without_eol": sum(v["life_hours"] is None for v in values),
        "settings": {"alpha": alpha, "lambda": lam, "horizon_alpha": horizon_alpha, "every_hours": float(every)},
    }
