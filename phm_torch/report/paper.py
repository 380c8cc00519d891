"""The end-to-end report: every stage's results beside the seed paper's, figure by figure."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from .html import HtmlReport

# The seed paper's figures (Berri, Dalla Vedova, Mainini), as fractions where they are rates.
PAPER = {
    "err_alpha_median": (0.02, "< 2 % at 22 modes"),
    "err_k": (0.05, "~5 % at 20 neurons"),
    "fdi_mae_max": (0.01, "at most ~1 % per parameter"),
    "classifier_accuracy": (0.982, "98.2 % (500 vectors)"),
    "missed_fault_rate": (0.0325, "3.25 %"),
    "false_alarm_rate": (0.0133, "1.33 %"),
    "healthy_fraction": (123 / 500, "123 of 500 healthy"),
}
TARGETS = {"err_alpha_median": "<= 1 %", "err_k": "<= 3 %", "fdi_mae_max": "<= 1 %", "classifier_accuracy": ">= 99 %",
           "missed_fault_rate": "<= 1 %"}


def _load(path: Path) -> dict[str, Any]:
    return json.loads(path.read_text()) if path.is_file() else {}


def build_report(run_dir: Path, metrics: dict[str, Any], studies: dict[str, Any]) -> Path:
    """Write ``run_dir/report/index.html`` from the stage outputs under ``run_dir`` and ``studies`` (figures
    computed by the report stage)."""
    r = HtmlReport("phm_torch end-to-end run, compared with the seed paper")
    r.paragraph("Every figure below was measured by this run (see metrics.json beside this report); the paper's "
                "figures are quoted from Berri, Dalla Vedova and Mainini. Rates and errors are in %.")
    tr, ev, gen = metrics.get("train", {}), metrics.get("evaluate", {}), metrics.get("generate", {})
    actuator = gen.get("actuator") or tr.get("actuator") or ev.get("actuator")
    command = gen.get("command") or tr.get("command") or ev.get("command")
    r.paragraph(f"Actuator: {actuator or 'not recorded'}; test command: {command or 'not recorded'} (name and "
                "SHA-256 of the values, as every artefact of the run records them). The paper's figures are for "
                "its own actuator and chirp: on another actuator they are a point of comparison, not a target.")
    r.section("Summary: ours, the paper's, the target")
    rows = []
    ours = {"err_alpha_median": tr.get("err_alpha_median"), "err_k": tr.get("err_k"),
            "fdi_mae_max": max(tr["fdi_mae"]) if tr.get("fdi_mae") else None,
            "classifier_accuracy": tr.get("classifier_accuracy"), "missed_fault_rate": tr.get("missed_fault_rate"),
            "false_alarm_rate": tr.get("false_alarm_rate"), "healthy_fraction": studies.get("healthy_fraction")}
    for key, (paper, text) in PAPER.items():
        value = ours.get(key)
        rows.append([key, None if value is None else round(100 * value, 3), text, TARGETS.get(key, "")])
    r.table(["figure", "ours [%]", "paper", "target"], rows)
    if gen:
        r.paragraph(f"Data: {json.dumps({k: v for k, v in gen.items() if not isinstance(v, (dict, list))})}")

    r.section("Gappy-POD coefficient error vs retained modes (paper: median < 2 % at 22 modes)")
    ea = studies.get("err_alpha")
    if ea:
        r.table(["n_modes", "median [%]", "q25 [%]", "q75 [%]"],
                [[x["n_modes"], 100 * x["median"], 100 * x["q25"], 100 * x["q75"]] for x in ea["rows"]])
        r.figure(ea["figure"], "err_alpha vs modes, at the selected sample points")

    r.section("Placement of the sample points over the first POD mode (paper Fig.: 30 SOM points)")
    r.figure(studies.get("placement"), "selected samples over the first mode")

    r.section("err_k and timings vs hidden neurons (paper: ~5 % at 20 neurons, no gain beyond)")
    hs = studies.get("hidden")
    if hs:
        r.table(["hidden", "err_k [%]", "train [s]", "eval [us]"],
                [[x["n_hidden"], 100 * x["err_k"], x["train_s"], x["eval_us"]] for x in hs["rows"]])
        r.figure(hs["figure"], "err_k, evaluation and training time vs hidden neurons")

    r.section("FDI error per fault parameter (paper: at most ~1 %, k1 best, k6 worst)")
    if tr.get("fdi_mae"):
        r.table(["k"] + [f"k{i + 1}" for i in range(8)], [["mean |error| [%]"] + [100 * v for v in tr["fdi_mae"]]])
    r.figure(studies.get("fdi_per_parameter"), "mean |k_i error| per parameter")

    r.section("Health classifier confusion table (paper Table: 98.2 % correct, 3.25 % missed faults)")
    conf = tr.get("confusion") or {}
    if conf:
        r.table(["entry", "ours"], [[k, v] for k, v in conf.items()])
    r.table(["rate", "ours [%]", "paper [%]"],
            [["accuracy", _pct(tr.get("classifier_accuracy")), 98.2],
             ["missed faults (faulty called healthy)", _pct(tr.get("missed_fault_rate")), 3.25],
             ["false alarms", _pct(tr.get("false_alarm_rate")), 1.33]])

    r.section("RUL vs expected RUL with the 5-95 % band (from the true k and from the full flow)")
    r.table(["metric", "ours"], [[k, v] for k, v in ev.items() if k.startswith("rul_")])
    r.paragraph("Delta_RUL = (RUL_95 - RUL_5) / RUL_50 of the reference, as the paper defines it. Targets: "
                "median err_RUL from the true k <= the median Delta_RUL; full flow <= 1.5x that; >= 90 % of "
                "reference RULs inside the predicted band.")
    r.figure(run_dir / "evaluate" / "rul_vs_expected.png", "RUL vs expected (reference median); shaded: reference 5-95 %")
    r.section("Three-panel RUL error comparison (paper Fig.: physics uncertainty, RUL step, full flow)")
    r.figure(run_dir / "evaluate" / "rul_errors.png", "uncertainty of the physics model / RUL step / full flow")

    r.section("Uncertainty of the online outputs: k_hat intervals and P(faulty) (not in the paper)")
    if ev.get("fdi_interval_coverage"):
        names = [f"k{i + 1}" for i in range(8)]
        widths = ev["fdi_interval_half_widths"]
        per_class = [[f"half-width, {c}{'+' if c == len(widths) - 1 else ''} large faults ({n} calibration records)"]
                     + list(w) for c, (w, n) in enumerate(zip(widths, ev["fdi_interval_counts"]))]
        r.table(["k_hat interval, evaluated split"] + names,
                [["coverage [%] (target 90 per parameter)"] + [100 * v for v in ev["fdi_interval_coverage"]],
                 ["mean width"] + list(ev["fdi_interval_width"])] + per_class)
    r.table(["P(faulty) on the evaluated split", "ours"],
            [[k, ev.get(k)] for k in ("verdict_brier", "verdict_brier_base_rate", "verdict_accuracy",
                                      "verdict_prior_faulty")])
    r.paragraph("Both are calibrated on the noisy val records (docs/prognostics.md): split-conformal half-widths "
                "per number of large faults of k_hat, and Platt scaling of the health score.")

    _life_section(r, run_dir)

    r.section("Online latencies (paper: milliseconds on a desktop; targets FDI <= 100 us, full step <= 1 ms)")
    lat = studies.get("latency", {})
    r.table(["quantity", "ours"], [["FDI p50 [us] (phm-train)", tr.get("fdi_latency_us_p50")]]
            + [[k, v] for k, v in lat.items()])

    wb = metrics.get("workbench", {})
    r.section("Workbench on the bundled hidden-effect measurement: before / after")
    wbr = _load(run_dir / "workbench" / "report.json")
    if wbr:
        cands = wbr.get("candidates", [])[:5]
        r.table(["effect", "score", "p-value", "significant", "NRMSE after refit"],
                [[c.get("effect"), c.get("score"), c.get("p_value"), c.get("significant"), c.get("nrmse_after_refit")]
                 for c in cands])
        r.table(["quantity", "value"], [["NRMSE (model as given)", json.dumps(wbr.get("nrmse"))],
                                        ["noise floor", json.dumps(wbr.get("noise_floor"))]]
                + [[k, json.dumps(v)] for k, v in wb.items() if not isinstance(v, (dict, list))])
        for png in sorted((run_dir / "workbench").glob("*.png"))[:6]:
            r.figure(png, png.stem)
    else:
        r.paragraph("(workbench stage not run)")
    cases = metrics.get("cases")
    if cases:
        r.section("Virtual bench: faulty actuators vs nominal (HF)")
        r.paragraph(json.dumps({k: v for k, v in cases.items() if k in ("nrmse", "wall_time_s")})[:2000])
        for png in sorted((run_dir / "cases").glob("*.png"))[:3]:
            r.figure(png, png.stem)
    return r.write(run_dir / "report" / "index.html")


LIFE_ROWS = (   # metric of phm_torch.prognostics.life_metrics, its label, its key in the targets block
    ("coverage_5_95", "true RUL inside the 5-95 % band", "coverage_5_95"),
    ("median_relative_band_width_second_half", "median (p95 - p5) / true RUL, second half of life",
     "median_relative_band_width_second_half"),
    ("alpha_lambda", "alpha-lambda accuracy (alpha 0.2, lambda 0.5)", "alpha_lambda"),
    ("relative_accuracy", "relative accuracy at lambda 0.5 (median)", None),
    ("prognostic_horizon", "prognostic horizon / life (median, alpha 0.1)", "prognostic_horizon"),
    ("eol_detection_delay", "end-of-life detection delay [h] (median)", None),
    ("eol_flagged_within_one_inspection", "end of life flagged within one inspection", "eol_flagged_within_one_inspection"),
    ("positive_p50_when_faulty", "positive RUL p50 on a faulty verdict (count)", "positive_p50_when_faulty"))


def _life_section(r: HtmlReport, run_dir: Path) -> None:
    """Life tracking (phm-track on the life split): the fused RUL against the single-record one (not in the
    paper: its RUL is a snapshot)."""
    scores = _load(run_dir / "track" / "metrics.json")
    r.section("Life tracking: inspections fused over each actuator's life vs one record at a time (not in the paper)")
    if not scores:
        r.paragraph("(track stage not run)")
        return
    targets = scores.get("targets", {})
    rows = []
    for key, label, target_key in LIFE_ROWS:
        t = targets.get(target_key) if target_key else None
        rows.append([label, scores["tracker"].get(key), scores["snapshot"].get(key),
                     "" if t is None else t["target"], "" if t is None else ("yes" if t["passed"] else "no")])
    r.table(["Saxena et al. (2010) metric", "tracker", "snapshot", "target", "met"], rows)
    r.paragraph(f"{scores.get('n_actuators')} actuators, {scores.get('n_inspections')} inspections "
                f"({scores.get('n_out_of_distribution')} out of distribution, not fused); metric definitions in "
                "docs/prognostics.md (Life tracking metrics). An empty cell is an infinite value (a censored band).")
    for name in ("life_rul", "life_damage", "life_fleet"):
        r.figure(run_dir / "track" / f"{name}.png", name.replace("_", " "))


def _pct(v: float | None) -> float | None:
    return None if v is None else 100 * v
