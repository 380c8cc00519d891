"""The end-to-end report of ``phm-run`` (``report/index.html``): every stage's results beside the seed paper's.

:func:`build_report` only lays out what the stages measured (``metrics``, the merged ``metrics.json``) and
what the report stage computed (``studies``: the offline figures of the paper and the pretrained pipeline run
on the bundled records); it computes nothing. Every table is a table (no JSON dumps); a row whose figure is
undefined (err_alpha at one mode) is left out and the page says why; a banner states the run's scale.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

from .html import HtmlReport
from .pretrained import pretrained_section
from .stage_sections import cases_section, life_section, percent, workbench_section

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
TARGETS = {
    "err_alpha_median": ("<=", 0.01),
    "err_k": ("<=", 0.03),
    "fdi_mae_max": ("<=", 0.01),
    "classifier_accuracy": (">=", 0.99),
    "missed_fault_rate": ("<=", 0.01),
}
LABELS = {
    "err_alpha_median": "gappy-POD coefficient error err_alpha, median",
    "err_k": "fault estimate error err_k",
    "fdi_mae_max": "largest mean |k_i error| of one parameter",
    "classifier_accuracy": "health classifier on the true k: accuracy",
    "missed_fault_rate": "health classifier: missed faults (faulty called healthy)",
    "false_alarm_rate": "health classifier: false alarms",
    "healthy_fraction": "healthy fraction of the training signals",
}
PAPER_N_TRAIN = 10_000  # the paper's training signals (conf/experiment/paper.yaml)
MIN_ERR_ALPHA_MODES = 2  # err_alpha divides by the range of the coefficients over the modes: 0 for one mode

RUL_ROWS = (  # key in the evaluate stage's metrics, label, unit ("%" of a fraction, "h", "" as is)
    ("rul_vectors", "RUL records evaluated", ""),
    ("rul_reference_faulty", "of them already faulty under the reference (RUL 0; left out of relative errors)", ""),
    ("rul_uncertainty_median", "Delta_RUL of the physics reference, median", "%"),
    ("rul_err_median_true_k", "RUL error from the true k, median (relative)", "%"),
    ("rul_err_median_hours_true_k", "RUL error from the true k, median (in hours)", "h"),
    ("rul_band_coverage_true_k", "reference RUL inside the band from the true k", "%"),
    ("rul_err_median_full_flow", "RUL error of the full flow (k_hat from the record), median", "%"),
    ("rul_band_coverage_full_flow", "reference RUL inside the full-flow band", "%"),
    ("rul_uncertainty_median_full_flow", "full-flow band width (p95 - p5) / p50, median", "%"),
    ("rul_underestimate_fraction", "full-flow RUL below the reference (conservative)", "%"),
    ("rul_untrustworthy_full_flow", "records with no full-flow RUL (out of distribution)", ""),
    ("rul_err_median_full_flow_physics_only", "RUL error of the full flow, physics-only band, median", "%"),
    ("rul_band_coverage_full_flow_physics_only", "reference RUL inside the physics-only full-flow band", "%"),
    ("rul_err_median_true_k_monte_carlo", "RUL error from the true k, Monte Carlo band, median", "%"),
    ("rul_band_coverage_true_k_monte_carlo", "reference RUL inside the Monte Carlo band from the true k", "%"),
    ("rul_band_coverage_true_k_initial_state", "reference RUL inside the initial-state band from the true k", "%"),
    ("rul_band_coverage_true_k_rate", "reference RUL inside the rate band from the true k", "%"),
    ("rul_band", "band model of the RUL", ""),
)
LATENCY_LABELS = {
    "online_step_us_p50": "online step (reloaded TorchScript), one signal, p50 [us]",
    "online_step_us_p99": "online step (reloaded TorchScript), one signal, p99 [us]",
    "online_batched_signals_per_s": "online step, batch of 1024 [signals/s]",
}


def _duration(seconds: float) -> str:
    return f"{seconds:.0f} s" if seconds < 120 else f"{int(seconds // 60)} min {seconds % 60:.0f} s"


def run_scale(metrics: dict[str, Any]) -> dict[str, Any]:
    """{n_train, n_val, n_rul, n_life, wall_s: {stage: s}, total_s} of a run, ``None`` where not recorded."""
    tr, splits = metrics.get("train", {}), metrics.get("generate", {}).get("splits", {})

    def count(key: str, split: str) -> int | None:
        return tr.get(key) if tr.get(key) is not None else (splits.get(split) or {}).get("count")

    wall = {k: float(v) for k, v in (metrics.get("wall_s") or {}).items()}
    return {
        "n_train": count("n_train", "train"),
        "n_val": count("n_val", "val"),
        "n_rul": (splits.get("rul") or {}).get("count"),
        "n_life": (metrics.get("generate", {}).get("life") or {}).get("actuators"),
        "wall_s": wall,
        "total_s": sum(wall.values()) if wall else None,
    }


def _banner(r: HtmlReport, metrics: dict[str, Any], repo: Path | None) -> None:
    s = run_scale(metrics)
    n = s["n_train"]
    size = (
        (f"{n:,} training signals" if n is not None else "an unrecorded number of training signals")
        + (
            f" ({s['n_val']:,} validation, {s['n_rul']:,} RUL)"
            if s["n_val"] is not None and s["n_rul"] is not None
            else ""
        )
        + (f" and {s['n_life']} run-to-failure histories" if s["n_life"] else "")
    )
    wall = (
        (
            f"its stages took {_duration(s['total_s'])} on this machine ("
            + ", ".join(f"{k} {_duration(v)}" for k, v in s["wall_s"].items())
            + ")"
        )
        if s["total_s"]
        else "its wall time was not recorded"
    )
    lines = [f"Scale of this run: {size}; {wall}."]
    if n is None:
        lines.append("This run's scale is not recorded (no generate or train metrics in metrics.json).")
    elif n >= PAPER_N_TRAIN:
        lines.append("This run is at the paper's data scale (phm-run experiment=paper: 10,000 training signals).")
    else:
        lines.append(
            f"This run is below the paper's data scale (it trains on {PAPER_N_TRAIN:,} signals): the default "
            "phm-run is the demo scale, sized to finish in minutes on a 2-core CPU. Its figures below show "
            "that every stage runs end to end, not what the method reaches."
        )
    lines.append(
        "Paper-scale figures (phm-run experiment=paper) and those of the pretrained pipeline (80,000 "
        "training signals): README.md, section 'Results against the seed paper', and pretrained/README.md. "
        "The section 'Pretrained pipeline on the bundled records' below runs that shipped pipeline here."
    )
    links = (
        []
        if repo is None
        else [
            ("README.md", (repo / "README.md").as_uri()),
            ("pretrained/README.md", (repo / "pretrained" / "README.md").as_uri()),
        ]
    )
    r.banner(lines, links)


def _met(key: str, value: float | None) -> str | None:
    if key not in TARGETS or value is None or not math.isfinite(value):
        return None
    op, bound = TARGETS[key]
    return "yes" if (value <= bound if op == "<=" else value >= bound) else "no"


def _summary(r: HtmlReport, metrics: dict[str, Any], studies: dict[str, Any]) -> None:
    tr = metrics.get("train", {})
    ours = {
        "err_alpha_median": tr.get("err_alpha_median"),
        "err_k": tr.get("err_k"),
        "fdi_mae_max": max(tr["fdi_mae"]) if tr.get("fdi_mae") else None,
        "classifier_accuracy": tr.get("classifier_accuracy"),
        "missed_fault_rate": tr.get("missed_fault_rate"),
        "false_alarm_rate": tr.get("false_alarm_rate"),
        "healthy_fraction": studies.get("healthy_fraction"),
    }
    r.section("Summary: ours, the paper's, the target")
    r.table(
        ["quantity", "ours [%]", "paper", "target", "met"],
        [
            [
                LABELS[key],
                None if ours[key] is None else round(100 * ours[key], 3),
                text,
                "" if key not in TARGETS else f"{TARGETS[key][0]} {100 * TARGETS[key][1]:g} %",
                _met(key, ours[key]),
            ]
            for key, (_, text) in PAPER.items()
        ],
    )
    r.note(
        "A dash: the stage that measures it was not run. The targets are the project's (README.md); at the "
        "demo scale they are not expected to be met."
    )


def _data(r: HtmlReport, gen: dict[str, Any]) -> None:
    if not gen:
        return
    r.section("Data (phm-generate)")
    splits = gen.get("splits") or {}
    r.table(
        ["split", "signals", "healthy", "healthy [%]"],
        [[name, s.get("count"), s.get("healthy"), percent(s.get("healthy_fraction"))] for name, s in splits.items()],
    )
    r.table(
        ["quantity", "value"],
        [
            ["wall time [s]", gen.get("wall_time_s")],
            ["HF signals per second", gen.get("signals_per_s")],
            ["assessment labels per second", gen.get("labels_per_s")],
            ["store fingerprint (SHA-256, first 16)", str(gen.get("fingerprint") or "")[:16] or None],
        ],
    )
    r.note("The labels split holds signals labelled by the assessment function only (for the health classifier).")


def _err_alpha(r: HtmlReport, ea: dict[str, Any] | None) -> None:
    r.section("Gappy-POD coefficient error vs retained modes (paper: median < 2 % at 22 modes)")
    if not ea:
        r.note("(not computed: the train stage's bundle or the data store is missing)")
        return
    rows = [x for x in ea["rows"] if x["n_modes"] >= MIN_ERR_ALPHA_MODES and math.isfinite(x["median"])]
    r.table(
        ["n_modes", "median [%]", "q25 [%]", "q75 [%]"],
        [[x["n_modes"], 100 * x["median"], 100 * x["q25"], 100 * x["q75"]] for x in rows],
    )
    if len(rows) < len(ea["rows"]):
        r.note(
            "err_alpha is the RMS coefficient error divided by the range (max - min) of the coefficients over the "
            "retained modes; with one mode that range is zero, so the figure is undefined and its row is left out."
        )
    r.figure(ea.get("figure"), "err_alpha vs modes, at the selected sample points")


def _classifier(r: HtmlReport, tr: dict[str, Any]) -> None:
    r.section("Health classifier confusion table (paper Table: 98.2 % correct, 3.25 % missed faults)")
    conf = tr.get("classifier_confusion") or {}
    if conf:
        r.table(
            ["validation records", "called healthy", "called faulty"],
            [
                ["healthy", conf.get("healthy_correct"), conf.get("false_alarms")],
                ["faulty", conf.get("missed_faults"), conf.get("faulty_correct")],
            ],
        )
    r.table(
        ["rate", "ours [%]", "paper [%]"],
        [
            ["accuracy", percent(tr.get("classifier_accuracy")), 98.2],
            ["missed faults (faulty called healthy)", percent(tr.get("missed_fault_rate")), 3.25],
            ["false alarms", percent(tr.get("false_alarm_rate")), 1.33],
            ["verdict from k_hat (the whole chain): accuracy", percent(tr.get("chain_accuracy")), None],
            ["verdict from k_hat: missed faults", percent(tr.get("chain_missed_fault_rate")), None],
            ["verdict from k_hat: false alarms", percent(tr.get("chain_false_alarm_rate")), None],
        ],
    )
    r.note(
        "The health classifier is given the true k of each validation record, as in the paper; the verdict "
        "from k_hat is what a measurement gets (the paper does not report it)."
    )


def _rul(r: HtmlReport, run_dir: Path, ev: dict[str, Any]) -> None:
    r.section("RUL vs expected RUL with the 5-95 % band (from the true k and from the full flow)")
    known = {key for key, _, _ in RUL_ROWS}
    rows = [[label, percent(ev[key]) if unit == "%" else ev[key], unit] for key, label, unit in RUL_ROWS if key in ev]
    rows += [[key, ev[key], ""] for key in ev if key.startswith("rul_") and key not in known]
    r.table(["quantity", "ours", "unit"], rows)
    r.note(
        "Delta_RUL = (RUL_95 - RUL_5) / RUL_50 of the reference, as the paper defines it. Targets: median "
        "err_RUL from the true k <= the median Delta_RUL; full flow <= 1.5x that; >= 90 % of reference RULs "
        "inside the predicted band. The full-flow band width is relative to its own p50, large where "
        "that p50 is near zero."
    )
    r.figure(
        run_dir / "evaluate" / "rul_vs_expected.png", "RUL vs expected (reference median); shaded: reference 5-95 %"
    )
    r.section("Three-panel RUL error comparison (paper Fig.: physics uncertainty, RUL step, full flow)")
    r.figure(run_dir / "evaluate" / "rul_errors.png", "uncertainty of the physics model / RUL step / full flow")


def _uncertainty(r: HtmlReport, ev: dict[str, Any]) -> None:
    r.section("Uncertainty of the online outputs: k_hat intervals and P(faulty) (not in the paper)")
    if ev.get("fdi_interval_coverage"):
        names = [f"k{i + 1}" for i in range(len(ev["fdi_interval_coverage"]))]
        widths = ev["fdi_interval_half_widths"]
        per_class = [
            [f"half-width, {c}{'+' if c == len(widths) - 1 else ''} large faults ({n} calibration records)"] + list(w)
            for c, (w, n) in enumerate(zip(widths, ev["fdi_interval_counts"]))
        ]
        r.table(
            ["k_hat interval, evaluated split"] + names,
            [
                ["coverage [%] (target 90 per parameter)"] + [100 * v for v in ev["fdi_interval_coverage"]],
                ["mean width"] + list(ev["fdi_interval_width"]),
            ]
            + per_class,
        )
    r.table(
        ["P(faulty) on the evaluated split", "ours"],
        [
            ["Brier score", ev.get("verdict_brier")],
            ["Brier score of the base rate (– where the split holds one class)", ev.get("verdict_brier_base_rate")],
            ["faulty fraction of the split", ev.get("verdict_faulty_fraction")],
            ["accuracy [%]", percent(ev.get("verdict_accuracy"))],
            ["prior P(faulty)", ev.get("verdict_prior_faulty")],
        ],
    )
    r.note(
        "Both are calibrated on the noisy val records (docs/prognostics.md): split-conformal half-widths per "
        "number of large faults of k_hat, and Platt scaling of the health score."
    )
    q = ev.get("held_out_quality")
    if q:
        r.table(
            [f"verdict on the held-out {q.get('split')} records (exported with the pipeline)", "ours"],
            [
                ["records", q.get("records")],
                ["out of distribution [%]", percent(q.get("out_of_distribution"))],
                [f"faulty answered healthy [%] (of {q.get('faulty_records')})", percent(q.get("missed_faulty"))],
                [f"healthy answered faulty [%] (of {q.get('healthy_records')})", percent(q.get("false_alarm"))],
            ],
        )
        r.note(
            "phm-predict gives each verdict the rate of its own kind (verdict_held_out_error) and warns once per run "
            "above 10 %; the classifiers' checkpoint was chosen and the FDI band calibrated on these records, so "
            "the rates lean to optimism."
        )


def build_report(run_dir: Path, metrics: dict[str, Any], studies: dict[str, Any], repo: Path | None = None) -> Path:
    """Write ``run_dir/report/index.html`` from the stage outputs under ``run_dir``, their merged ``metrics``
    (``wall_s`` holding the stages run so far) and the report stage's ``studies``; ``repo`` is the
    repository root the banner links to (``None``: no links)."""
    r = HtmlReport("phm_torch end-to-end run, compared with the seed paper")
    _banner(r, metrics, repo)
    tr, ev, gen = metrics.get("train", {}), metrics.get("evaluate", {}), metrics.get("generate", {})
    actuator = gen.get("actuator") or tr.get("actuator") or ev.get("actuator")
    command = gen.get("command") or tr.get("command") or ev.get("command")
    r.paragraph(
        f"Actuator: {actuator or 'not recorded'}; test command: {command or 'not recorded'} (name and "
        "SHA-256 of the values, as every artefact of the run records them). Every figure below was measured "
        "by this run (metrics.json beside this report); the paper's are quoted from Berri, Dalla Vedova "
        "and Mainini, for its own actuator and chirp: on another actuator they are a point of comparison, "
        "not a target."
    )
    _summary(r, metrics, studies)
    pretrained_section(r, studies.get("pretrained"))
    _data(r, gen)
    _err_alpha(r, studies.get("err_alpha"))

    r.section("Placement of the sample points over the first POD mode (paper Fig.: 30 SOM points)")
    r.figure(studies.get("placement"), "selected samples over the first mode")

    r.section("err_k and timings vs hidden neurons (paper: ~5 % at 20 neurons, no gain beyond)")
    hs = studies.get("hidden")
    if hs:
        r.table(
            ["hidden neurons", "err_k [%]", "train [s]", "eval [us]"],
            [[x["n_hidden"], 100 * x["err_k"], x["train_s"], x["eval_us"]] for x in hs["rows"]],
        )
        r.figure(hs["figure"], "err_k, evaluation and training time vs hidden neurons")

    r.section("FDI error per fault parameter (paper: at most ~1 %, k1 best, k6 worst)")
    if tr.get("fdi_mae"):
        r.table(
            ["k"] + [f"k{i + 1}" for i in range(len(tr["fdi_mae"]))],
            [["mean |error| [%]"] + [100 * v for v in tr["fdi_mae"]]],
        )
    r.figure(studies.get("fdi_per_parameter"), "mean |k_i error| per parameter")

    _classifier(r, tr)
    _rul(r, run_dir, ev)
    _uncertainty(r, ev)
    life_section(r, run_dir, metrics.get("companions"))

    r.section("Online latencies (paper: milliseconds on a desktop; targets FDI <= 100 us, full step <= 1 ms)")
    lat = studies.get("latency", {})
    r.table(
        ["quantity", "ours"],
        [["FDI, one signal, p50 [us] (phm-train)", tr.get("fdi_latency_us_p50")]]
        + [[LATENCY_LABELS.get(k, k), v] for k, v in lat.items()],
    )

    workbench_section(r, run_dir, metrics.get("workbench", {}))
    cases_section(r, run_dir, metrics.get("cases"))
    return r.write(run_dir / "report" / "index.html")
