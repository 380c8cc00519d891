"""Prognostic metrics of life tracks (Saxena et al. 2010) on hand-built tracks with known answers."""

from __future__ import annotations

import copy
import json
import math

import numpy as np
import pytest

from phm_torch.prognostics import life_metrics as lm

EVERY = 200.0


def _q(p5, p50, p95):
    return {"p5": p5, "p50": p50, "p95": p95}


def _band(rul, lo, mid, hi):
    """A band scaled on the true RUL, clipped at 0 (after EOL every quantile is 0)."""
    r = max(rul, 0.0)
    return _q(lo * r, mid * r, hi * r)


def make_life(eols, tracker=(0.5, 1.0, 1.5), snapshot=(1.9, 2.0, 2.1), after=2):
    """truth and track dicts in issue 25's format: inspections every 200 h from 0 to two after EOL;
    the tracker's and snapshot's quantiles are fixed multiples of the true RUL; healthy until EOL."""
    truth = {"every_hours": EVERY, "actuators": {}}
    track = {"actuators": {}}
    for n, eol in enumerate(eols):
        a = f"A{n:03d}"
        hours = [EVERY * i for i in range(int(eol // EVERY) + 1 + after)]
        truth["actuators"][a] = {
            "rate_scale": 1.0,
            "eol_hours": eol,
            "k0": [0.0] * 8,
            "inspections": [
                {"hours": h, "file": f"{a}_{i}.csv", "k_true": [0.0] * 8, "healthy": h < eol, "rul_true": eol - h}
                for i, h in enumerate(hours)
            ],
        }
        track["actuators"][a] = {
            "inspections": [
                {
                    "hours": h,
                    "file": f"{a}_{i}.csv",
                    "healthy": h < eol,
                    "p_faulty": float(h >= eol),
                    "rul_hours": _band(eol - h, *tracker),
                    "rul_censored": False,
                    "out_of_distribution": False,
                    "fused": True,
                    "snapshot_rul_hours": _band(eol - h, *snapshot),
                    "snapshot_rul_censored": False,
                }
                for i, h in enumerate(hours)
            ]
        }
    return track, truth


# ---------------------------------------------------------------- array functions


def test_lambda_index_takes_first_inspection_at_or_after_t_lambda():
    hours = np.arange(0.0, 1200.0, 200.0)
    assert lm.lambda_index(hours, 0.0, 1050.0, 0.5) == 3  # t_lambda = 525 -> 600
    assert lm.lambda_index(hours, 0.0, 1000.0, 0.4) == 2  # t_lambda = 400 exactly
    assert lm.lambda_index(hours[:2], 0.0, 1050.0, 0.5) is None


def test_alpha_lambda_cone_edges():
    hours = np.array([0.0, 200.0, 400.0, 600.0, 800.0])
    true = 1050.0 - hours  # 450 h at the lambda inspection (600 h)
    good, bad = true.copy(), true.copy()
    good[3], bad[3] = 450.0 * 1.19, 450.0 * 1.21
    assert lm.alpha_lambda(hours, true, good, 0.0, 1050.0, 0.2, 0.5) is True
    assert lm.alpha_lambda(hours, true, bad, 0.0, 1050.0, 0.2, 0.5) is False
    bad[2] = bad[4] = 0.0  # other inspections do not matter
    good[2] = good[4] = 0.0
    assert lm.alpha_lambda(hours, true, good, 0.0, 1050.0, 0.2, 0.5) is True


def test_relative_accuracy_values():
    ra = lm.relative_accuracy(np.array([100.0, 100.0, 100.0, 100.0]), np.array([100.0, 80.0, 150.0, np.inf]))
    np.testing.assert_allclose(ra[:3], [1.0, 0.8, 0.5])
    assert ra[3] == -np.inf


def test_prognostic_horizon_is_sustained():
    hours = np.array([0.0, 200.0, 400.0, 600.0, 800.0])
    true = 1000.0 - hours
    # bounds +- 0.1 x 1000 = 100 h: in, out, in, in, in -> the horizon starts at 400 h, not at 0 h
    pred = true + np.array([50.0, 150.0, -99.0, 0.0, 100.0])
    assert lm.prognostic_horizon(hours, true, pred, 1000.0, 1000.0, 0.1) == pytest.approx(600.0)
    assert lm.prognostic_horizon(hours, true, true, 1000.0, 1000.0, 0.1) == pytest.approx(1000.0)
    last_out = true + np.array([0.0, 0.0, 0.0, 0.0, 101.0])
    assert lm.prognostic_horizon(hours, true, last_out, 1000.0, 1000.0, 0.1) == 0.0


def test_coverage_width_and_censored_bounds():
    true = np.array([100.0, 100.0, 100.0, 100.0])
    p5 = np.array([50.0, 101.0, 50.0, np.inf])
    p95 = np.array([150.0, 150.0, np.inf, np.inf])
    np.testing.assert_array_equal(lm.covered(true, p5, p95), [True, False, True, False])
    w = lm.relative_band_width(true, p5, p95)
    np.testing.assert_allclose(w[:2], [1.0, 0.49])
    assert np.isinf(w[2]) and np.isinf(w[3])


def test_eol_detection_delay():
    hours = np.array([0.0, 200.0, 400.0, 600.0])
    assert lm.eol_detection_delay(hours, np.array([0, 0, 1, 1]), 350.0) == pytest.approx(50.0)
    assert lm.eol_detection_delay(hours, np.array([0, 1, 1, 1]), 350.0) == pytest.approx(-150.0)
    assert math.isinf(lm.eol_detection_delay(hours, np.zeros(4), 350.0))


# ---------------------------------------------------------------- evaluate_life on hand-built tracks


def test_perfect_tracker_against_biased_snapshot():
    track, truth = make_life([1050.0, 1450.0])
    r = lm.evaluate_life(track, truth)
    t, s = r["tracker"], r["snapshot"]
    assert t["alpha_lambda"] == 1.0 and t["relative_accuracy"] == pytest.approx(1.0)
    assert t["prognostic_horizon"] == pytest.approx(1.0)  # the whole life
    assert t["prognostic_horizon_hours"] == pytest.approx(1250.0)  # median of 1050 and 1450
    assert t["coverage_5_95"] == 1.0
    assert t["median_relative_band_width_second_half"] == pytest.approx(1.0)  # (1.5 - 0.5) by construction
    assert t["eol_detection_delay"] == pytest.approx(150.0)  # EOL 1050 -> 1200, 1450 -> 1600
    assert t["eol_flagged_within_one_inspection"] == 1.0 and t["positive_p50_when_faulty"] == 0
    # the snapshot p50 is twice the truth: outside the cone, RA = 0, band [1.9, 2.1] x RUL misses it
    assert s["alpha_lambda"] == 0.0 and s["relative_accuracy"] == pytest.approx(0.0)
    assert s["coverage_5_95"] == 0.0
    assert s["median_relative_band_width_second_half"] == pytest.approx(0.2)
    # PH bounds +- 105 h (A000): only the 1000 h inspection (RUL 50 h, error 50 h) is inside -> 50 h
    assert r["per_actuator"]["A000"]["snapshot"]["prognostic_horizon_hours"] == pytest.approx(50.0)
    assert s["positive_p50_when_faulty"] is None  # no snapshot verdict in the track
    tg = r["targets"]
    assert tg["coverage_5_95"]["passed"] and tg["alpha_lambda"]["passed"] and tg["prognostic_horizon"]["passed"]
    assert tg["median_relative_band_width_second_half"]["passed"]  # 1.0 <= 1.0
    assert not tg["band_width_ratio_to_snapshot"]["passed"]
    assert tg["band_width_ratio_to_snapshot"]["value"] == pytest.approx(5.0)
    assert not r["all_targets_passed"]
    assert r["n_actuators"] == 2 and r["n_inspections"] == 6 + 2 + 8 + 2


def test_biased_tracker_fails_targets():
    track, truth = make_life([1050.0, 1450.0, 2050.0], tracker=(1.25, 1.3, 1.35))
    r = lm.evaluate_life(track, truth)
    assert r["tracker"]["alpha_lambda"] == 0.0
    assert r["tracker"]["coverage_5_95"] == 0.0
    assert r["tracker"]["relative_accuracy"] == pytest.approx(0.7)
    failed = {k for k, v in r["targets"].items() if not v["passed"]}
    assert {"coverage_5_95", "alpha_lambda", "prognostic_horizon"} <= failed


def test_censored_bounds_count_as_infinite():
    track, truth = make_life([1050.0])
    insp = track["actuators"]["A000"]["inspections"]
    for i in insp[3:6]:  # second half (>= 525 h): 600, 800, 1000 h
        i["rul_hours"]["p95"] = None
        i["rul_censored"] = True
    insp[0]["rul_hours"] = None  # every bound beyond the horizon: p5 = +inf misses the truth
    r = lm.evaluate_life(track, truth)
    a = r["per_actuator"]["A000"]["tracker"]
    assert a["coverage_5_95"] == pytest.approx(5 / 6)
    assert a["median_relative_band_width_second_half"] is None  # +inf, written as null
    assert r["tracker"]["median_relative_band_width_second_half"] is None
    assert r["tracker"]["relative_band_width_second_half_censored"] == 1.0
    assert r["snapshot"]["relative_band_width_second_half_censored"] == 0.0
    assert not r["targets"]["median_relative_band_width_second_half"]["passed"]
    assert not r["targets"]["band_width_ratio_to_snapshot"]["passed"]
    json.dumps(r, allow_nan=False)  # strict JSON: no Infinity


def test_eol_delay_in_inspections_and_early_flags():
    track, truth = make_life([1050.0, 1050.0, 1050.0], tracker=(0.5, 1.0, 1.5))
    for n, a in enumerate(("A000", "A001", "A002")):
        for i in track["actuators"][a]["inspections"]:
            i["rul_hours"]["p50"] = max(1050.0 - i["hours"], 1.0)  # never 0: only the verdict flags
            # A000 flagged at 1200 h (first after EOL), A001 at 1400 h (two late), A002 at 600 h (early)
            i["healthy"] = i["hours"] < (1200.0, 1400.0, 600.0)[n]
    r = lm.evaluate_life(track, truth)
    per = r["per_actuator"]
    assert per["A000"]["tracker"]["eol_detection_delay_hours"] == pytest.approx(150.0)
    assert per["A001"]["tracker"]["eol_detection_delay_hours"] == pytest.approx(350.0)
    assert per["A002"]["tracker"]["eol_detection_delay_hours"] == pytest.approx(-450.0)
    assert [per[a]["tracker"]["eol_flagged_within_one_inspection"] for a in per] == [True, False, False]
    assert r["tracker"]["eol_flagged_within_one_inspection"] == pytest.approx(1 / 3)
    assert r["tracker"]["eol_flagged_early"] == pytest.approx(1 / 3)
    # how far beyond one interval, in intervals: A001 350 h late = 0.75, A002 450 h early = 1.25, A000 none
    assert [per[a]["tracker"]["eol_intervals_late"] for a in per] == pytest.approx([0.0, 0.75, 0.0])
    assert [per[a]["tracker"]["eol_intervals_early"] for a in per] == pytest.approx([0.0, 0.0, 1.25])
    assert r["tracker"]["eol_intervals_late"] == pytest.approx(0.25)
    assert r["tracker"]["eol_intervals_early"] == pytest.approx(1.25 / 3)
    # the verdict says faulty while p50 >= 1 h: A000 at 1200, 1400; A001 at 1400; A002 at 600..1400
    assert r["tracker"]["positive_p50_when_faulty"] == 2 + 1 + 5
    assert not r["targets"]["positive_p50_when_faulty"]["passed"]


def test_never_flagged_is_infinite_delay():
    track, truth = make_life([1050.0])
    for i in track["actuators"]["A000"]["inspections"]:
        i["healthy"] = True
        i["rul_hours"] = _q(10.0, 20.0, None)
    r = lm.evaluate_life(track, truth)
    assert r["per_actuator"]["A000"]["tracker"]["eol_detection_delay_hours"] is None
    assert r["tracker"]["eol_never_flagged"] == 1 and r["tracker"]["eol_flagged_within_one_inspection"] == 0.0
    # counted as flagged one interval after the last inspection (1400 h): 550 h late, 1.75 intervals
    assert r["tracker"]["eol_intervals_late"] == pytest.approx(1.75) and r["tracker"]["eol_intervals_early"] == 0.0
    json.dumps(r, allow_nan=False)


def test_out_of_distribution_inspections_are_excluded_but_counted():
    track, truth = make_life([1050.0])
    base = lm.evaluate_life(track, truth)
    insp = track["actuators"]["A000"]["inspections"]
    for i in (insp[1], insp[4]):
        i.update(out_of_distribution=True, fused=False, rul_hours=_q(1e5, 2e5, 3e5))
    r = lm.evaluate_life(track, truth)
    assert r["n_out_of_distribution"] == 2
    for key in ("coverage_5_95", "alpha_lambda", "prognostic_horizon", "median_relative_band_width_second_half"):
        assert r["tracker"][key] == base["tracker"][key]
    assert r["tracker"]["coverage_5_95_n"] == base["tracker"]["coverage_5_95_n"] - 2


def test_a_run_without_eol_is_counted_not_scored():
    track, truth = make_life([1050.0, 1450.0])
    truth["actuators"]["A001"]["eol_hours"] = None
    r = lm.evaluate_life(track, truth)
    assert r["n_without_eol"] == 1 and r["tracker"]["alpha_lambda_n"] == 1


def test_calibrated_lognormal_predictor_covers_90_percent():
    """p50 = RUL_true exp(sigma z), band p50 exp(+-1.645 sigma): the truth lies in the band iff |z| <= 1.645
    (90 %), the relative width has median 2 sinh(1.645 sigma) and alpha-lambda is P(|sigma z| <~ alpha)."""
    rng = np.random.default_rng(0)
    sigma, zq = 0.1, 1.645
    eols = list(rng.uniform(2000.0, 6000.0, 60).round())
    track, truth = make_life(eols)
    for a, t in track["actuators"].items():
        for i in t["inspections"]:
            rul = max(truth["actuators"][a]["eol_hours"] - i["hours"], 0.0)
            m = rul * math.exp(sigma * rng.standard_normal())
            i["rul_hours"] = _q(m * math.exp(-zq * sigma), m, m * math.exp(zq * sigma))
    r = lm.evaluate_life(track, truth)["tracker"]
    n = r["coverage_5_95_n"]
    assert n > 800 and abs(r["coverage_5_95"] - 0.90) < 3 * math.sqrt(0.09 / n)
    assert r["median_relative_band_width_second_half"] == pytest.approx(2 * math.sinh(zq * sigma), rel=0.05)
    # within the 20 % cone: log-ratio in [log 0.8, log 1.2] = [-2.23, 1.82] sigma -> 0.953
    assert r["alpha_lambda"] == pytest.approx(0.953, abs=0.08)


# ---------------------------------------------------------------- bad input


@pytest.mark.parametrize(
    "edit, message",
    [
        (lambda tr, gt: tr["actuators"].update(B999=tr["actuators"]["A000"]), "'B999' is in the track"),
        (lambda tr, gt: gt["actuators"].pop("A001"), "'A001' is in the track but not in the truth"),
        (lambda tr, gt: tr["actuators"].pop("A001"), "'A001' is in the truth but not in the track"),
        (lambda tr, gt: tr["actuators"]["A001"]["inspections"][2].update(hours=401.0), "'A001' inspection 2"),
        (lambda tr, gt: tr["actuators"]["A000"]["inspections"].pop(), "'A000' has 7 inspections in the track"),
        (lambda tr, gt: gt.update(every_hours=0), "every_hours must be > 0, got 0"),
        (lambda tr, gt: gt["actuators"]["A000"].update(eol_hours=math.inf), "'A000' eol_hours = inf"),
    ],
)
def test_input_validation_names_the_actuator_and_value(edit, message):
    track, truth = make_life([1050.0, 1450.0])
    track, truth = copy.deepcopy(track), copy.deepcopy(truth)
    edit(track, truth)
    with pytest.raises(ValueError, match=message.replace("(", r"\(")):
        lm.evaluate_life(track, truth)


@pytest.mark.parametrize("kwargs", [{"alpha": 0.0}, {"alpha": 1.5}, {"lam": -0.1}, {"horizon_alpha": 0.0}])
def test_bad_settings(kwargs):
    track, truth = make_life([1050.0])
    name = next(iter(kwargs))
    with pytest.raises(ValueError, match=f"{name} = "):
        lm.evaluate_life(track, truth, **kwargs)


# ---------------------------------------------------------------- figures


def test_plot_life_writes_figures_and_fleet_table(tmp_path):
    from phm_torch.faults import FAULT_NAMES
    from phm_torch.prognostics.life_plots import fleet_rows, plot_life, readings, select_actuators

    track, truth = make_life([1050.0, 1450.0, 2050.0])
    for n, a in enumerate(truth["actuators"]):
        truth["actuators"][a]["rate_scale"] = (1.5, 0.7, 1.0)[n]
        for g, i in zip(truth["actuators"][a]["inspections"], track["actuators"][a]["inspections"]):
            g["k_true"][0] = 1e-4 * g["hours"]
            i["k_hat"] = {name: (1.1e-4 * g["hours"] if j == 0 else 0.0) for j, name in enumerate(FAULT_NAMES)}
            i["k_filtered"] = {name: (1e-4 * g["hours"] if j == 0 else 0.0) for j, name in enumerate(FAULT_NAMES)}
            i["k_interval"] = {FAULT_NAMES[0]: [0.9e-4 * g["hours"], 1.2e-4 * g["hours"]]}
            i["k_filtered_interval"] = {FAULT_NAMES[0]: [0.95e-4 * g["hours"], 1.05e-4 * g["hours"]]}
    track["actuators"]["A000"]["inspections"][1]["k_interval"] = None  # one inspection without
    # what the filter read, where it is not k_hat: the near-nominal FDI's reading, k_hat through the response's inverse
    a1 = track["actuators"]["A001"]["inspections"]
    a1[0]["k_hat_near_nominal"], a1[0]["k_hat_near_nominal_interval"] = {"backlash": 0.02}, {"backlash": [0.01, 0.04]}
    a1[1]["k_hat_corrected"], a1[1]["k_hat_corrected_interval"] = {"backlash": 0.05}, {"backlash": [0.03, 0.06]}
    centre, bars = readings(a1, "backlash")
    assert centre[:2].tolist() == [0.02, 0.05] and centre[2] == a1[2]["k_hat"]["backlash"]
    assert bars[:, 0] == pytest.approx([0.01, 0.02]) and bars[:, 1] == pytest.approx([0.02, 0.01])
    k_hat_bars = readings(track["actuators"]["A000"]["inspections"], FAULT_NAMES[0])[1]
    assert np.isnan(k_hat_bars[:, 1]).all() and np.isfinite(k_hat_bars[:, 0]).all()  # its k_interval is None
    last = track["actuators"]["A001"]["inspections"][-1]
    last["rul_hours"] = None  # censored: listed last in the fleet
    paths = plot_life(track, truth, tmp_path, max_actuators=2)
    assert [p.name for p in paths] == ["life_rul.png", "life_damage.png", "life_fleet.csv", "life_fleet.png"]
    assert all(p.stat().st_size > 1000 for p in paths if p.suffix == ".png")
    # two of three, spread over the wear-rate scale: the slowest (A001, s 0.7) and the fastest (A000, s 1.5)
    assert select_actuators(truth, 2) == ["A001", "A000"]
    rows = fleet_rows(track, truth)
    assert [r["actuator"] for r in rows] == ["A000", "A002", "A001"]
    assert rows[-1]["rul_p5"] is None and rows[0]["rul_true"] == pytest.approx(1050.0 - 1400.0)
    text = (tmp_path / "life_fleet.csv").read_text().splitlines()
    assert text[0].startswith("actuator,hours,rul_p5") and len(text) == 4
    with pytest.raises(ValueError, match="max_actuators must be an int >= 1, got 0"):
        plot_life(track, truth, tmp_path, max_actuators=0)


def test_the_life_figures_name_the_actuator_and_command(tmp_path, monkeypatch):
    from phm_torch.prognostics import life_plots

    track, truth = make_life([1050.0, 1450.0])
    assert life_plots.whose(track) == ""  # a track.json without provenance: no title added
    track["actuator"] = {"name": "lin28", "sha256": "faf2dde1"}
    track["command"] = {"name": "chirp_lin28", "sha256": "a7894df2"}
    assert life_plots.whose(track) == "lin28 / chirp_lin28"
    titles = []
    save = life_plots.save_figure

    def capture(fig, path):
        heading = fig._suptitle.get_text() if fig._suptitle is not None else fig.axes[0].get_title()
        titles.append(heading)
        return save(fig, path)

    monkeypatch.setattr(life_plots, "save_figure", capture)
    life_plots.plot_life(track, truth, tmp_path, max_actuators=2)
    assert len(titles) == 3 and all(t.startswith("lin28 / chirp_lin28") for t in titles)
