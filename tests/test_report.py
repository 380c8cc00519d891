"""The phm-run report built from a small fake run (no stage is run): tables, never JSON dumps; the banner with
the run's scale; err_alpha's undefined one-mode row left out with the reason; the pretrained section. And the
report stage's pretrained study on the bundled example record (the shipped pipeline, about 2 s)."""

from __future__ import annotations

import html
import json
import re

import pytest

from phm_torch.apps.run import compose_stage, pretrained_study
from phm_torch.report.html import HtmlReport, fmt
from phm_torch.report.paper import build_report

NOMINAL = [0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.5, 0.5]
K_NAMES = [
    "dry_friction",
    "backlash",
    "short_a",
    "short_b",
    "short_c",
    "eccentricity",
    "eccentricity_phase",
    "gain_drift",
]


def _metrics(n_train: int) -> dict:
    return {
        "generate": {
            "actuator": "ema_reference (sha256 6a5886d0)",
            "command": "chirp (sha256 367940da)",
            "fingerprint": "804ebf29e04d11ef2fa9986df8ffbe9e",
            "wall_time_s": 73.6,
            "signals_per_s": 19.6,
            "splits": {
                "train": {"count": n_train, "healthy": 166, "healthy_fraction": 0.2767},
                "val": {"count": 100, "healthy": 23, "healthy_fraction": 0.23},
                "rul": {"count": 30, "healthy": 26, "healthy_fraction": 0.8667},
            },
        },
        "train": {
            "n_train": n_train,
            "n_val": 100,
            "err_alpha_median": 0.0504,
            "err_k": 0.1138,
            "fdi_mae": [0.05, 0.06, 0.06, 0.04, 0.04, 0.13, 0.26, 0.04],
            "classifier_accuracy": 0.98,
            "missed_fault_rate": 0.013,
            "false_alarm_rate": 0.0435,
            "classifier_confusion": {
                "healthy_correct": 22,
                "faulty_correct": 76,
                "missed_faults": 1,
                "false_alarms": 1,
            },
        },
        "evaluate": {"rul_vectors": 30, "rul_err_median_true_k": 0.0196, "rul_band": "rate", "rul_new_metric": 0.5},
        "workbench": {
            "nrmse_after": {"current": 0.0249, "total": 0.0177},
            "best_candidate": "cogging_torque",
            "added": ["cogging_torque"],
            "timing": {"total_s": 98.9},
        },
        "cases": {
            "fidelity": "hf",
            "duration": 0.5,
            "wall_time_s": 53.0,
            "nominal": {"faults": NOMINAL},
            "cases": {
                "k1_friction": {
                    "faults": [0.5, *NOMINAL[1:]],
                    "nrmse_current": 0.0549,
                    "nrmse_position": 0.0012,
                    "peak_current": 2.41,
                }
            },
        },
        "wall_s": {"cases": 59.3, "generate": 169.6, "train": 83.1, "evaluate": 72.8},
    }


def _pretrained() -> dict:
    k_hat = dict(zip(K_NAMES, [0.5, 0.001, 0.0, 0.003, 0.002, 0.005, 0.538, 0.499]))
    pred = {
        "k_hat": k_hat,
        "healthy": False,
        "p_faulty": 0.998,
        "rul_hours": {"p5": 0.0, "p50": 0.0, "p95": None},
        "out_of_distribution": False,
        "noise": 0.00015,
        "noise_above_calibration": False,
        "k_not_identified": [],
    }
    return {
        "pipeline": "pretrained/online_surrogates_best.pt",
        "actuator": "ema_reference (sha256 6a5886d0)",
        "command": "chirp (sha256 367940da)",
        "skipped": None,
        "notes": [],
        "records": [
            {
                "name": "k1_friction.csv",
                "source": "virtual bench (hf, noise-free): k1_friction",
                "true_k": {"dry_friction": 0.5},
                "prediction": pred,
            }
        ],
    }


def _studies() -> dict:
    rows = [
        {"n_modes": 1, "median": 1.3e38, "q25": 6e37, "q75": 3e38},  # range of one coefficient: 0
        {"n_modes": 2, "median": 0.04995, "q25": 0.027, "q75": 0.113},
        {"n_modes": 22, "median": 0.05044, "q25": 0.028, "q75": 0.082},
    ]
    return {
        "err_alpha": {"rows": rows, "figure": None},
        "healthy_fraction": 0.2767,
        "latency": {"online_step_us_p50": 2046.0},
        "pretrained": _pretrained(),
    }


def _tables(page: str) -> list[list[list[str]]]:
    """Every table of the page as rows of unescaped cell texts."""
    return [
        [
            [html.unescape(c) for c in re.findall(r"<t[dh]>(.*?)</t[dh]>", row)]
            for row in re.findall(r"<tr>(.*?)</tr>", table)
        ]
        for table in re.findall(r"<table>(.*?)</table>", page)
    ]


@pytest.fixture
def run_dir(tmp_path):
    (tmp_path / "workbench").mkdir()
    (tmp_path / "workbench" / "report.json").write_text(
        json.dumps(
            {
                "nrmse": {"position": 0.00203, "current": 0.0279, "total": 0.0198},
                "noise_floor": {"position": 0.00203, "current": 0.0192, "total": 0.0137},
                "candidates": [
                    {
                        "effect": "cogging_torque",
                        "label": "cogging_torque",
                        "score": 709.1,
                        "p_value": 3.7e-152,
                        "significant": True,
                        "nrmse_after_refit": 0.0177,
                    }
                ],
            }
        )
    )
    return tmp_path


def test_the_report_has_tables_not_json_and_a_banner_with_the_scale(run_dir):
    page = build_report(run_dir, _metrics(600), _studies(), repo=run_dir).read_text()
    # no JSON object pasted into the page ("Data: {...}", "NRMSE (model as given) {...}")
    assert not re.search(r"\{\s*(&quot;|\")", page) and "Data: " not in page
    banner = html.unescape(re.search(r'<div class="banner">(.*?)</div>', page).group(1))
    assert "600 training signals (100 validation, 30 RUL)" in banner
    assert "6 min 25 s" in banner  # 59.3 + 169.6 + 83.1 + 72.8 s of stages
    assert "demo scale" in banner and "README.md" in banner and "pretrained/README.md" in banner
    assert page.index('class="banner"') < page.index("<h2>")  # at the top
    tables = _tables(page)
    # the workbench's NRMSE per channel as a table in %, not a dict
    channel = next(t for t in tables if t[0][0] == "channel")
    assert ["current", "2.79", "1.92", "2.49"] == channel[2]
    # the confusion table as a 2 x 2 table, an unknown RUL metric still shown under its own name
    assert ["faulty", "1", "76"] in next(t for t in tables if t[0][0] == "validation records")
    assert any(row[0] == "rul_new_metric" for t in tables for row in t)


def test_the_undefined_one_mode_err_alpha_row_is_left_out_and_explained(run_dir):
    page = build_report(run_dir, _metrics(600), _studies()).read_text()
    err_alpha = next(t for t in _tables(page) if t[0][0] == "n_modes")
    assert [row[0] for row in err_alpha[1:]] == ["2", "22"] and err_alpha[1][1] == "4.995"
    assert "e+3" not in page  # no 1e38 % anywhere
    assert "with one mode that range is zero, so the figure is undefined" in html.unescape(page)


def test_the_banner_says_paper_scale_for_a_paper_scale_run(run_dir):
    banner = re.search(
        r'<div class="banner">(.*?)</div>', build_report(run_dir, _metrics(10000), _studies()).read_text()
    ).group(1)
    assert "10,000 training signals" in banner and "paper&#x27;s data scale" in banner
    assert "demo scale" not in banner
    unknown = re.search(r'<div class="banner">(.*?)</div>', build_report(run_dir, {}, {}).read_text()).group(1)
    assert "scale is not recorded" in unknown and "wall time was not recorded" in unknown


def test_the_pretrained_section_shows_verdicts_k_hat_and_rul(run_dir):
    page = build_report(run_dir, _metrics(600), _studies()).read_text()
    verdicts = next(t for t in _tables(page) if t[0][0] == "record")
    assert verdicts[1][:5] == [
        "k1_friction.csv",
        "virtual bench (hf, noise-free): k1_friction",
        "dry_friction 0.5 (k_hat 0.500)",
        "faulty",
        "99.8",
    ]
    assert verdicts[1][5:8] == ["0", "0", "> horizon"]  # a censored p95 is not a number
    k_hat = next(t for t in _tables(page) if t[0][0] == "k_hat")
    assert k_hat[0][1:] == K_NAMES and k_hat[1][1] == "0.5"
    skipped = {**_studies(), "pretrained": {**_pretrained(), "skipped": "it is for the actuator ema_reference"}}
    page = build_report(run_dir, _metrics(600), skipped).read_text()
    assert "(not run: it is for the actuator ema_reference" in html.unescape(page)


def test_cells_are_formatted_in_one_place():
    assert fmt({"position": 0.00203, "total": 0.0198}) == "position 0.00203; total 0.0198"
    assert (fmt(None), fmt(True), fmt(["a", 1.23456]), fmt(float("inf"))) == ("–", "yes", "a, 1.235", "inf")
    r = HtmlReport("t")
    with pytest.raises(ValueError, match=r"rows\[0\] has 1 cells, the header 2"):
        r.table(["a", "b"], [[1]])


@pytest.mark.torchscript
def test_the_report_stage_runs_the_pretrained_pipeline_on_the_bundled_record(tmp_path):
    cfg = compose_stage("run", [f"out_dir={tmp_path}"])
    short = {"cases": {"duration": 0.05, "cases": {}}}  # a tiny run's bench: not the pipeline's length
    study = pretrained_study(cfg, tmp_path, short)
    assert study["skipped"] is None and "0.05 s" in study["notes"][0]
    (record,) = study["records"]
    assert record["name"] == "workbench_hidden_cogging.csv" and "hidden cogging_torque" in record["source"]
    pred = record["prediction"]
    # a nominal actuator with a hidden cogging torque: no damaging fault read from it
    assert max(pred["k_hat"][n] for n in K_NAMES[:6]) < 0.1 and abs(pred["k_hat"]["gain_drift"] - 0.5) < 0.05
    assert pred["healthy"] and not pred["out_of_distribution"]
    other = compose_stage("run", [f"out_dir={tmp_path}", "actuator.coulomb_friction=0.012"])
    assert "it is for the actuator ema_reference" in pretrained_study(other, tmp_path, {})["skipped"]


def test_the_life_section_says_what_the_companions_stage_gave_the_tracker(run_dir):
    (run_dir / "track").mkdir()
    scores = {"tracker": {"coverage_5_95": 0.86}, "snapshot": {"coverage_5_95": 0.99}, "targets": {}}
    (run_dir / "track" / "metrics.json").write_text(json.dumps({**scores, "n_actuators": 6, "n_inspections": 90}))
    companions = {
        "life_actuators": 40,
        "life_inspections": 772,
        "response": "evaluate/online.fdi_response.json",
        "tracker_rule": {
            "verdict": "posterior",
            "faulty_at": "p5",
            "rules": {
                "record/p50": {
                    "eol_flagged_within_one_inspection": 0.225,
                    "eol_flagged_late_or_never": 0.075,
                    "eol_intervals_early": 3.1,
                    "eol_intervals_late": 0.004,
                },
                "posterior/p5": {"eol_flagged_within_one_inspection": 0.7, "eol_flagged_late_or_never": 0.05},
            },
        },
    }
    text = html.unescape(build_report(run_dir, {**_metrics(600), "companions": companions}, _studies()).read_text())
    assert "made from 40 histories of their own (772 inspections" in text
    assert "an FDI response, a near-nominal FDI, and the end-of-life rule posterior/p5, chosen there" in text
    assert "record/p50 22.5 %, 7.5 %, 3.10 / 0.00; posterior/p5 70 %, 5 %, - / -)" in text  # a run before the intervals
    without = html.unescape(build_report(run_dir, _metrics(600), _studies()).read_text())
    assert "histories of their own" not in without
    skipped = {**companions, "tracker_rule": None, "near_nominal_skipped": "6 held-out records within the gate"}
    text = html.unescape(build_report(run_dir, {**_metrics(600), "companions": skipped}, _studies()).read_text())
    assert "no near-nominal FDI (6 held-out records within the gate: the pipeline's k_hat read near nominal" in text
    assert "the tracker's default end-of-life rule" in text  # a run before the stage chose one without the FDI
    chose = {**companions, "near_nominal_skipped": "6 held-out records within the gate"}
    text = html.unescape(build_report(run_dir, {**_metrics(600), "companions": chose}, _studies()).read_text())
    assert "read near nominal too), and the end-of-life rule posterior/p5, chosen there" in text


def test_the_life_section_puts_the_tracking_limit_beside_the_tracker(run_dir):
    (run_dir / "track").mkdir()
    scores = {"tracker": {"prognostic_horizon": 0.574}, "snapshot": {"prognostic_horizon": 0.1}, "targets": {}}
    limit = {
        "error_std": 1e-4,
        "tracking": {"prognostic_horizon": 0.623},
        "classifier_on_true_k": {"eol_flagged_within_one_inspection": 0.96},
    }
    (run_dir / "track" / "metrics.json").write_text(json.dumps({**scores, "limit": limit, "n_actuators": 100}))
    text = html.unescape(build_report(run_dir, _metrics(600), _studies()).read_text())
    assert "tracker fed the true k (±0.0001)" in text and "0.623" in text
    assert "flags 96 % of the ends of life within one inspection" in text
    (run_dir / "track" / "metrics.json").write_text(json.dumps({**scores, "limit": None, "n_actuators": 100}))
    without = html.unescape(build_report(run_dir, _metrics(600), _studies()).read_text())
    assert "fed the true k" not in without and "0.574" in without
