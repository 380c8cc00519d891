"""Sections of the ``phm-run`` report (:mod:`phm_torch.report.paper`) for the stages after the surrogates: the
workbench on its hidden-effect record, the virtual bench's cases and the life tracking. Each lays out what its
stage wrote under ``run_dir``; none computes anything."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from .html import HtmlReport, fmt


def load_json(path: Path) -> dict[str, Any]:
    """A stage's JSON file, ``{}`` where the stage did not write it."""
    return json.loads(path.read_text()) if path.is_file() else {}


def percent(v: float | None) -> float | None:
    """A fraction in percent (None stays None)."""
    return None if v is None else 100 * v


def workbench_section(r: HtmlReport, run_dir: Path, wb: dict[str, Any]) -> None:
    r.section("Workbench on the bundled hidden-effect measurement: before / after")
    wbr = load_json(run_dir / "workbench" / "report.json")
    if not wbr:
        r.note("(workbench stage not run)")
        return
    r.table(
        ["effect", "score", "p-value", "significant", "NRMSE after refit [%]"],
        [
            [
                c.get("label") or c.get("effect"),
                c.get("score"),
                c.get("p_value"),
                c.get("significant"),
                percent(c.get("nrmse_after_refit")),
            ]
            for c in wbr.get("candidates", [])[:5]
        ],
    )
    nrmse, floor, after = wbr.get("nrmse") or {}, wbr.get("noise_floor") or {}, wb.get("nrmse_after") or {}
    r.table(
        ["channel", "NRMSE, model as given [%]", "noise floor [%]", "NRMSE, effects added [%]"],
        [[c, percent(nrmse.get(c)), percent(floor.get(c)), percent(after.get(c))] for c in nrmse],
    )
    timing = wb.get("timing") or {}
    r.table(
        ["quantity", "value"],
        [
            ["most likely missing effect", wb.get("best_candidate")],
            ["effects added", wb.get("added") or "none"],
            ["neural closure's lead input", wb.get("closure_lead")],
            ["wall time [s]", timing.get("total_s")],
        ],
    )
    r.markup(
        '<p class="note">The workbench\'s own page, with every diagnostic: '
        '<a href="../workbench/report.html">workbench/report.html</a>.</p>'
    )
    for png in ("before_after", "candidates", "overlay"):
        if (run_dir / "workbench" / f"{png}.png").is_file():
            r.figure(run_dir / "workbench" / f"{png}.png", png.replace("_", " "))


def cases_section(r: HtmlReport, run_dir: Path, cases: dict[str, Any] | None) -> None:
    if not cases:
        return
    from ..faults import FAULT_NAMES

    r.section("Virtual bench: faulty actuators vs nominal")
    nominal = (cases.get("nominal") or {}).get("faults") or []
    rows = []
    for name, c in (cases.get("cases") or {}).items():
        changed = {
            FAULT_NAMES[i]: v for i, v in enumerate(c.get("faults") or []) if i >= len(nominal) or v != nominal[i]
        }
        rows.append(
            [
                name,
                changed or "none",
                percent(c.get("nrmse_current")),
                percent(c.get("nrmse_position")),
                c.get("peak_current"),
            ]
        )
    r.table(
        ["case", "faults (differing from nominal)", "NRMSE current [%]", "NRMSE position [%]", "peak current [A]"], rows
    )
    r.note(
        f"{str(cases.get('fidelity', '')).upper()} records of {cases.get('duration')} s; NRMSE = RMS(case - "
        f"nominal) / range of the nominal signal, noise-free; simulated in {cases.get('wall_time_s')} s."
    )
    for png in sorted((run_dir / "cases").glob("*.png"))[:3]:
        r.figure(png, png.stem)


LIFE_ROWS = (  # metric of phm_torch.prognostics.life_metrics, its label, its key in the targets block
    ("coverage_5_95", "true RUL inside the 5-95 % band", "coverage_5_95"),
    (
        "median_relative_band_width_second_half",
        "median (p95 - p5) / true RUL, second half of life",
        "median_relative_band_width_second_half",
    ),
    ("alpha_lambda", "alpha-lambda accuracy (alpha 0.2, lambda 0.5)", "alpha_lambda"),
    ("relative_accuracy", "relative accuracy at lambda 0.5 (median)", None),
    ("prognostic_horizon", "prognostic horizon / life (median, alpha 0.1)", "prognostic_horizon"),
    ("eol_detection_delay", "end-of-life detection delay [h] (median)", None),
    (
        "eol_flagged_within_one_inspection",
        "end of life flagged within one inspection",
        "eol_flagged_within_one_inspection",
    ),
    ("positive_p50_when_faulty", "positive RUL p50 on a faulty verdict (count)", "positive_p50_when_faulty"),
)


def life_section(r: HtmlReport, run_dir: Path, companions: dict[str, Any] | None = None) -> None:
    """Life tracking (phm-track on the life split): the fused RUL against the single-record one (not in the
    paper: its RUL is a snapshot); ``companions``: the companions stage's metrics (what the tracker read besides
    the pipeline), when it ran."""
    scores = load_json(run_dir / "track" / "metrics.json")
    r.section("Life tracking: inspections fused over each actuator's life vs one record at a time (not in the paper)")
    if not scores:
        r.note("(track stage not run)")
        return
    if companions:
        rule = companions.get("tracker_rule") or {}

        def pct(v: float | None) -> str:
            return "-" if v is None else f"{fmt(100 * v)} %"

        def intervals(v: float | None) -> str:
            return "-" if v is None else f"{v:.2f}"

        r.note(
            f"The tracker read the companions stage's files, made from {companions.get('life_actuators')} histories of "
            f"their own ({companions.get('life_inspections')} inspections, not the ones scored here): "
            + ("an FDI response, " if companions.get("response") else "no FDI response (too few inspections), ")
            + (
                f"no near-nominal FDI ({companions['near_nominal_skipped']}: the pipeline's k_hat read near nominal "
                "too), "
                if companions.get("near_nominal_skipped")
                else "a near-nominal FDI, "
            )
            + (
                f"and the end-of-life rule {rule.get('verdict')}/{rule.get('faulty_at')}, "
                + "chosen there (ends of life flagged within one inspection, late or never, and the mean inspection "
                + "intervals flagged early / late beyond one: "
                + "; ".join(
                    f"{name} {pct(f.get('eol_flagged_within_one_inspection'))}, "
                    f"{pct(f.get('eol_flagged_late_or_never'))}, "
                    f"{intervals(f.get('eol_intervals_early'))} / {intervals(f.get('eol_intervals_late'))}"
                    for name, f in (rule.get("rules") or {}).items()
                )
                + ")."
                if rule.get("verdict")
                else "and the tracker's default end-of-life rule."
            )
        )
        seen = companions.get("tracker_check_figures")
        if seen:
            r.note(
                "On those histories the tracker, as phm-track runs it beside this pipeline, held the true RUL in its "
                f"5-95 % band on {pct(seen.get('coverage_5_95'))} of the inspections and flagged "
                f"{pct(seen.get('eol_flagged_early'))} of the ends of life early: written beside the pipeline "
                "(.tracker_check.json), phm-track warns of either below 70 % / above 50 %."
            )
    targets = scores.get("targets", {})

    limit = scores.get("limit")  # the same filter fed the true k (phm-track's limit_error_std), when computed

    def value(block: dict[str, Any], key: str) -> Any:
        """A metric recorded as null is infinite; one not recorded, a dash."""
        v = block.get(key)
        return "∞" if v is None and key in block else v

    rows = []
    for key, label, target_key in LIFE_ROWS:
        t = targets.get(target_key) if target_key else None
        limit_cell = [value(limit["tracking"], key)] if limit else []
        rows.append(
            [
                label,
                value(scores["tracker"], key),
                *limit_cell,
                value(scores["snapshot"], key),
                "" if t is None else t["target"],
                "" if t is None else t["passed"],
            ]
        )
    limit_head = [f"tracker fed the true k (±{limit['error_std']:g})"] if limit else []
    r.table(["Saxena et al. (2010) metric", "tracker", *limit_head, "snapshot", "target", "met"], rows)
    if limit:
        flagged = limit["classifier_on_true_k"]["eol_flagged_within_one_inspection"]
        r.note(
            "The tracker fed the true k is what these histories leave to know with this damage law and health "
            "classifier: a target it misses, no FDI reaches here. The health classifier on the true k flags "
            f"{'-' if flagged is None else f'{fmt(100 * flagged)} %'} of the ends of life within one inspection "
            "(docs/prognostics.md, 'What the histories leave to know')."
        )
    r.note(
        f"{scores.get('n_actuators')} actuators, {scores.get('n_inspections')} inspections "
        f"({scores.get('n_out_of_distribution')} out of distribution, not fused); metric definitions in "
        "docs/prognostics.md (Life tracking metrics). ∞: an infinite value (a censored band)."
    )
    for name in ("life_rul", "life_damage", "life_fleet"):
        r.figure(run_dir / "track" / f"{name}.png", name.replace("_", " "))
