"""Model-vs-measurement workbench (issue 6): unit tests of its statistics, bad input, and the loop end to end.

Default run (a few minutes on 2 cores): numpy-level checks of the noise floor, Levenberg-Marquardt, score
variance and diagnostics; every bad input refused before any simulation; then three short LF loops on
0.2 s chirp records: a hidden cogging torque through the ``phm-workbench`` app (report files), a control with
nothing missing, and the cross-fidelity case (LF model against the first 0.2 s of the shipped HF demo file).
The full-length cases (five hidden effects, two at once, the neural closure, the whole demo) are in
``tests/test_workbench_slow.py`` (``-m slow``).
"""

from __future__ import annotations

import base64
import json
import math
from pathlib import Path

import numpy as np
import pytest
import torch

from phm_torch.command import Chirp
from phm_torch.fitting import Problem, fit
from phm_torch.io import Measurement, read_measurement, write_measurement
from phm_torch.params import load_actuator
from phm_torch.workbench import (
    Case,
    HighBandNoise,
    Workbench,
    WorkbenchSettings,
    load_records,
    record_from_measurement,
    synthesize,
)
from phm_torch.workbench.candidates import chi2_logsf, newey_west
from phm_torch.workbench.closure import ClosureNet, attribute
from phm_torch.workbench.diagnostics import (
    Coordinates,
    DiagnosticSettings,
    cross_correlation,
    harmonics,
    whiteness,
    worst_windows,
)

P = load_actuator()
REPO = Path(__file__).resolve().parent.parent
DEMO = REPO / "examples" / "workbench_hidden_cogging.csv"
SHORT = 0.2  # [s] records of the default tests
NOISE = {"current": 0.02, "position": 2e-5}


# ---- statistics and numerics (no simulation) ------------------------------------------------------------
def test_noise_floor_reads_white_noise_under_a_band_limited_signal():
    rng = np.random.default_rng(0)
    t = np.arange(10001) / 20000.0
    smooth = 2.0 * np.sin(2 * np.pi * 7 * t * (1 + 20 * t)) + 0.3 * np.sin(2 * np.pi * 400 * t)
    for sigma in (0.005, 0.02, 0.1):
        est = HighBandNoise()(smooth + sigma * rng.standard_normal(t.size), 20000.0)
        assert abs(est / sigma - 1) < 0.05, (sigma, est)
    with pytest.raises(ValueError, match="noise.band"):
        HighBandNoise(band=(0.3, 0.2))


def test_batched_levenberg_marquardt_fits_two_problems_sharing_calls():
    """y = a exp(-b t) + noise; two problems solved together; the Laplace std matches the scatter of x."""
    t = torch.linspace(0, 1, 200, dtype=torch.float64)
    gen = torch.Generator().manual_seed(1)
    truth = [(2.0, 3.0), (0.5, 1.0)]
    data = [a * torch.exp(-b * t) + 0.01 * torch.randn(200, generator=gen, dtype=torch.float64) for a, b in truth]
    calls = []

    def evaluate(items):
        calls.append(sorted({j for j, _ in items}))
        return [((x[:, :1] * torch.exp(-x[:, 1:] * t) - data[j]) / 0.01, list(range(len(x)))) for j, x in items]

    problems = [
        Problem(
            torch.tensor([1.0, 1.0]), torch.tensor([0.0, 0.0]), torch.tensor([10.0, 10.0]), torch.tensor([1e-6, 1e-6])
        )
        for _ in truth
    ]
    res = fit(evaluate, problems, max_iter=30, tol_abs=1e-6, tol_rel=1e-10)
    for r, (a, b) in zip(res, truth, strict=True):
        std = r.std()
        assert abs(r.x[0] - a) < 4 * std[0] and abs(r.x[1] - b) < 4 * std[1], (r.x, std)
        assert 0.5 < r.chi2 / 198 < 1.5
    assert calls[0] == [0, 1] and calls[1] == [0, 1]  # one call per iteration serves both problems
    assert len(calls) <= 1 + 30


def test_newey_west_reduces_to_the_white_variance_and_grows_for_coloured_scores():
    rng = np.random.default_rng(2)
    white = rng.standard_normal((20000, 2))
    v = newey_west(white, 50)
    assert np.allclose(v / 20000, np.eye(2), atol=0.06)
    coloured = np.convolve(rng.standard_normal(20000), np.ones(20), mode="same")[:, None]
    assert newey_west(coloured, 50)[0, 0] > 10 * float(coloured[:, 0] @ coloured[:, 0])
    assert chi2_logsf(5000.0, 3) < -2400 and math.isfinite(chi2_logsf(1e5, 1))


def test_diagnostics_find_the_slot_harmonic_the_worst_window_and_non_white_residuals():
    rng = np.random.default_rng(3)
    n, fs = 8001, 20000.0
    t = np.arange(n) / fs
    angle = 1.0 * np.sin(2 * np.pi * 5 * t)  # +-1 rad of rotor travel, as on the test chirp
    speed = np.gradient(angle) * fs
    coords = [Coordinates(speed, angle, np.abs(np.cos(2 * np.pi * 5 * t)), np.ones(n))]
    noise = rng.standard_normal(n)
    ripple = 0.8 * np.sin(24 * angle + 0.3)
    settings = DiagnosticSettings()
    h = harmonics([{"current": ripple + noise}], coords, 48)["current"]
    assert int(np.argmax(h)) + 1 == 24
    burst = noise.copy()
    burst[3000:3400] += 3.0
    w = worst_windows([{"current": burst}], [{"current": 10 * np.sin(t)}], ["r"], fs, 0.02, 2)
    assert w[0]["t_start"] <= 3000 / fs <= w[0]["t_end"] + 0.01
    white = whiteness([{"current": noise, "position": np.convolve(noise, np.ones(8), "same")}], settings)
    assert white["current"]["white"] and not white["position"]["white"]
    xc = cross_correlation([{"current": noise}], [np.sin(2 * np.pi * 3 * t)], settings)
    assert xc["current"]["uncorrelated"]
    xc = cross_correlation([{"current": noise + 2 * np.sin(2 * np.pi * 3 * t)}], [np.sin(2 * np.pi * 3 * t)], settings)
    assert not xc["current"]["uncorrelated"]


def test_closure_attribution_names_the_input_it_uses():
    net = ClosureNet((1, 24), 6, speed_scale=50.0, current_scale=2.0, angle_scale=5e-3)
    theta = torch.linspace(-1, 1, 4000, dtype=torch.float64)
    feats = net.features(theta, 50 * torch.cos(3 * theta), torch.sin(theta), 5e-3 * theta)
    w = torch.zeros(net.n_weights, dtype=torch.float64)
    w[1 + 2] = 3.0  # sin(24 theta_m)
    shares = attribute(net, w, feats).shares
    assert next(iter(shares)) == "theta_m harmonic 24" and shares["theta_m harmonic 24"] > 0.99


# ---- bad input: refused with a ValueError naming the file/field, before any simulation -------------------
def _measurement(n: int = 4001, **change) -> Measurement:
    t = np.arange(n) / 20000.0
    cmd = 5e-3 * np.sin(2 * np.pi * 5 * t)
    m = Measurement(t, cmd, 0.9 * cmd, 1.0 + np.abs(np.sin(2 * np.pi * 5 * t)), {}, 20000.0)
    for k, v in change.items():
        setattr(m, k, v)
    return m


@pytest.fixture(scope="module")
def good_csv(tmp_path_factory) -> Path:
    path = tmp_path_factory.mktemp("wb_bad") / "good.csv"
    write_measurement(path, _measurement())
    return path


def _edit(path: Path, tmp: Path, name: str, edit) -> Path:
    lines = path.read_text().splitlines()
    out = tmp / name
    out.write_text("\n".join(edit(lines)) + "\n")
    return out


@pytest.mark.parametrize(
    "name, edit, match",
    [
        (
            "missing.csv",
            lambda ls: [",".join(x.split(",")[:3]) for x in ls],
            r"missing required column\(s\) \['current'\]",
        ),
        ("nonuniform.csv", lambda ls: ls[:100] + ls[101:], r"not uniformly sampled at line 101"),
        ("backwards.csv", lambda ls: ls[:50] + [ls[51], ls[50]] + ls[52:], r"not strictly increasing at line"),
        (
            "nan.csv",
            lambda ls: ls[:10] + [ls[10].rsplit(",", 1)[0] + ",nan"] + ls[11:],
            r"line 11, column 'current'.*not finite",
        ),
        (
            "inf.csv",
            lambda ls: ls[:10] + [ls[10].split(",", 1)[0] + ",inf," + ls[10].split(",", 2)[2]] + ls[11:],
            r"column 'command'.*not finite",
        ),
        (
            "rate.csv",
            lambda ls: [ls[0]] + [",".join([repr(float(x.split(",")[0]) * 2), *x.split(",")[1:]]) for x in ls[1:]],
            r"sample rate 10000 Hz .*differs from the expected 20000 Hz; pass resample=True",
        ),
    ],
)
def test_bad_csv_is_refused(good_csv, tmp_path, name, edit, match):
    with pytest.raises(ValueError, match=match):
        load_records(_edit(good_csv, tmp_path, name, edit), P, ["position", "current"])


def test_other_rate_is_resampled_only_on_request(good_csv, tmp_path):
    path = _edit(
        good_csv,
        tmp_path,
        "rate.csv",
        lambda ls: [ls[0]] + [",".join([repr(float(x.split(",")[0]) * 2), *x.split(",")[1:]]) for x in ls[1:]],
    )
    rec = load_records(path, P, ["position", "current"], resample=True)[0]
    assert rec.sample_rate == 20000.0 and len(rec) == 8001


@pytest.mark.parametrize(
    "change, channels, match",
    [
        ({"command": np.full(4001, 0.6)}, ["position", "current"], r"command' = 0.6 rad .*end stops .*end_stop_angle"),
        (
            {"position": 0.9 * 5e-3 * np.sin(2 * np.pi * 5 * np.arange(4001) / 2e4) + 2e-3},
            ["position", "current"],
            r"position' starts at 0.0020.* rad .*at rest at 0 rad",
        ),
        ({}, ["position", "speed"], r"channel\(s\) \['speed'\] requested by channels= are not in the file"),
        ({}, ["position", "torque"], r"channels: \['torque'\] cannot be compared"),
        ({"current": np.ones(4001)}, ["position", "current"], r"column 'current' is constant"),
        (
            {"sample_rate": 10000.0},
            ["position", "current"],
            r"sample rate 10000 Hz differs from the model's .*sample_rate",
        ),
    ],
)
def test_record_that_does_not_fit_the_model_is_refused(change, channels, match):
    with pytest.raises(ValueError, match=match):
        record_from_measurement(_measurement(**change), P, channels, "bad")


def test_too_short_and_missing_files_are_refused(tmp_path):
    with pytest.raises(ValueError, match=r"too short"):
        record_from_measurement(_measurement(n=100), P, ["position", "current"], "short")
    with pytest.raises(ValueError, match=r"no such measurement file"):
        load_records(tmp_path / "nope.csv", P, ["position"])
    with pytest.raises(ValueError, match=r"measurements: no file given"):
        load_records([], P, ["position"])


@pytest.mark.parametrize(
    "overrides, match",
    [
        (["free=[motor_inertia,bogus]"], r"free: unknown parameter 'bogus'"),
        (["free=[k9]"], r"free: unknown parameter 'k9'"),
        (["free=[k8,k8]"], r"listed twice"),
        (["+effects.no_such_effect={}"], r"unknown effect 'no_such_effect'"),
        (["+effects.cogging_torque.amplitude=-1"], r"effects.cogging_torque.amplitude"),
        (["library=[cogging_torque,warp_drive]"], r"library: unknown effect\(s\) \['warp_drive'\]"),
        (["fidelity=mf"], r"fidelity must be one of"),
        (["score.alpha=2"], r"score.alpha"),
        (["closure.enabled=maybe"], r"closure.enabled"),
        (["groups.dry_friction=[coulomb_friction,grip]"], r"groups.dry_friction: unknown"),
        (["scale_bounds=[2.0,5.0]"], r"scale_bounds must satisfy"),
        (["noise.band=[0.4,0.2]"], r"noise.band"),
        (["refit.free.cogging_torque=[amplitude,colour]"], r"refit_free.cogging_torque: unknown parameter"),
    ],
)
def test_bad_configuration_is_refused_before_simulating(compose, good_csv, tmp_path, overrides, match):
    from phm_torch.apps.workbench import run_workbench

    cfg = compose("workbench", [f"measurements={good_csv}", f"out_dir={tmp_path}", *overrides])
    with pytest.raises(ValueError, match=match):
        run_workbench(cfg)
    assert not (tmp_path / "report.json").exists()


# ---- the loop, short records ---------------------------------------------------------------------------
@pytest.fixture(scope="module")
def short_records(tmp_path_factory) -> dict[str, Path]:
    """Hidden cogging and a control (nothing missing), LF, 0.2 s chirp, noisy; one batched simulation."""
    cmd = Chirp(duration=SHORT)
    cases = {
        "cogging": Case({"cogging_torque": {"amplitude": 4e-3, "phase": 0.7}}, NOISE, seed=11),
        "control": Case({}, NOISE, seed=12),
    }
    out = tmp_path_factory.mktemp("wb_short")
    paths = {}
    for (name, _), m in zip(cases.items(), synthesize(P, list(cases.values()), cmd, SHORT), strict=True):
        paths[name] = write_measurement(out / f"{name}.csv", m)
    return paths


def quick_settings(**kw) -> WorkbenchSettings:
    from omegaconf import OmegaConf

    from phm_torch.apps.workbench import settings_from_config
    from phm_torch.params import CONF_DIR

    cfg = OmegaConf.load(CONF_DIR / "workbench.yaml")
    settings, _ = settings_from_config(cfg)
    return WorkbenchSettings(**{**settings.__dict__, **kw})


def test_app_finds_hidden_cogging_and_the_error_falls_to_the_noise_floor(compose, short_records, tmp_path):
    from phm_torch.apps.workbench import run_workbench

    out = tmp_path / "wb"
    metrics, objects = run_workbench(
        compose("workbench", [f"measurements={short_records['cogging']}", f"out_dir={out}", "refit.rounds=1"])
    )
    report = json.loads((out / "report.json").read_text())
    assert report == objects["report"]
    for key in ("nrmse", "noise_floor", "worst_windows", "candidates", "fitted", "before_after"):
        assert key in report, key
    assert set(report["nrmse"]) == {"position", "current", "total"}
    assert report["worst_windows"] and {"t_start", "t_end", "nrmse"} <= set(report["worst_windows"][0])
    assert set(report["fitted"]) == {"motor_inertia", "dry_friction", "k8"}
    assert all(len(v) == 2 and v[1] > 0 for v in report["fitted"].values())
    best = report["candidates"][0]
    assert best["effect"] == "cogging_torque" and best["significant"], report["candidates"][:3]
    assert [c["effect"] for c in report["candidates"] if c["significant"]] == ["cogging_torque"]
    assert best["evidence"]["pattern"] == "harmonic" and best["evidence"]["harmonic"] == 24, best["evidence"]
    floor = report["noise_floor"]
    assert report["nrmse"]["total"] > 1.5 * floor["total"]  # the model misses something
    after = best["nrmse_after_refit_channels"]
    assert after["total"] <= 1.2 * floor["total"] and after["current"] <= 1.2 * floor["current"], (after, floor)
    amp = best["fitted"]["cogging_torque.amplitude"]
    assert abs(amp[0] - 4e-3) < max(4 * amp[1], 2e-4), amp
    rows = report["before_after"]
    assert [r["model"] for r in rows] == ["model", "model + cogging_torque"]
    assert not rows[0]["white"] and rows[1]["nrmse"]["total"] < rows[0]["nrmse"]["total"]
    # the next step, training the surrogates on that physics: a phm-generate override with the fitted values
    fitted_amp = report["final"]["effects"]["cogging_torque"]["amplitude"]
    assert report["retrain"].startswith("'+dataset.effects.cogging_torque={amplitude: ")
    html = (out / "report.html").read_text()
    assert "phm-generate" in html and f"{fitted_amp:.6g}" in html
    assert html.count("data:image/png;base64,") >= 6
    png = html.split("data:image/png;base64,")[1].split('"')[0]
    assert base64.b64decode(png)[:8] == b"\x89PNG\r\n\x1a\n"
    assert (out / "overlay.png").stat().st_size > 1000 and metrics["best_candidate"] == "cogging_torque"


def test_control_with_nothing_missing_raises_no_significant_candidate(short_records):
    wb = Workbench(P, settings=quick_settings(rounds=1, refit_top=1))
    res = wb.run(wb.load(short_records["control"]))
    assert not [c.effect for c in res.candidates if c.significant], [(c.effect, c.p_value) for c in res.candidates]
    m = res.metrics["model"]
    assert m["nrmse"]["total"] <= 1.05 * m["noise_floor"]["total"]
    assert res.closure is None and res.added == []


def test_cross_fidelity_lf_model_finds_the_effect_hidden_in_hf_data():
    """LF model against the HF demo file (hidden cogging, current noise 0.05 A), first 0.2 s."""
    full = read_measurement(DEMO, expected_rate=P.sample_rate)
    n = round(SHORT * P.sample_rate) + 1
    cut = Measurement(full.time[:n], full.command[:n], full.position[:n], full.current[:n], {}, full.sample_rate)
    wb = Workbench(P, settings=quick_settings(rounds=1))
    res = wb.run([record_from_measurement(cut, P, ["position", "current"], "demo_head")])
    best = res.candidates[0]
    assert best.effect == "cogging_torque" and best.significant, [(c.effect, c.log10_p) for c in res.candidates]
    before, after = res.metrics["model"], res.metrics["model + cogging_torque"]
    assert after["nrmse"]["current"] < 0.8 * before["nrmse"]["current"]
    assert after["nrmse"]["total"] <= 1.2 * after["noise_floor"]["total"], (after["nrmse"], after["noise_floor"])


def test_several_records_of_different_lengths_are_fitted_together():
    """Two records (0.05 s and 0.08 s): one simulator call per length per iteration, one joint residual."""
    ms = [synthesize(P, [Case({}, NOISE, seed=s)], Chirp(duration=d), d)[0] for s, d in ((1, 0.05), (2, 0.08))]
    recs = [record_from_measurement(m, P, ["position", "current"], f"r{i}") for i, m in enumerate(ms)]
    wb = Workbench(P, settings=quick_settings(calibration=quick_settings().calibration.__class__(max_iter=2)))
    ev = wb.evaluator(recs)
    assert ev.m == 2 * (1001 + 1601) and len(ev.groups) == 2
    cal = wb.calibrate(ev)
    assert ev.calls == 2 * (1 + cal.result.iterations)
    assert cal.result.residual.shape == (ev.m,) and len(cal.simulated) == 2
    assert 0.7 < cal.chi2 / ev.m < 1.3  # nothing missing: the residual is the noise
    assert [len(e["current"]) for e in cal.errors()] == [1001, 1601]


def test_hf_model_calibrates_on_a_short_record():
    m = synthesize(P, [Case({}, NOISE, seed=3)], Chirp(duration=0.02), 0.02, fidelity="hf")[0]
    rec = record_from_measurement(m, P, ["position", "current"], "hf")
    wb = Workbench(
        P,
        fidelity="hf",
        free=["dry_friction"],
        settings=quick_settings(calibration=quick_settings().calibration.__class__(max_iter=1)),
    )
    cal = wb.calibrate(wb.evaluator([rec]))
    assert math.isfinite(cal.chi2) and 0.7 < cal.chi2 / len(cal.result.residual) < 1.3
    assert set(cal.fitted()) == {"dry_friction"}


def test_retrain_overrides_compose_into_the_dataset_spec(compose):
    from hydra.utils import instantiate

    from phm_torch.workbench.report import generate_overrides

    line = generate_overrides(
        {
            "aero_hinge_load": {"stiffness": 1015.0133, "bias": 0.98963921},
            "cogging_torque": {"amplitude": 0.0041, "phase": -0.3},
        }
    )
    assert line == (
        "'+dataset.effects.aero_hinge_load={stiffness: 1015.01, bias: 0.989639}' "
        "'+dataset.effects.cogging_torque={amplitude: 0.0041, phase: -0.3}'"
    )
    spec = instantiate(compose("generate", [o.strip("'") for o in line.split(" '")]).dataset)
    assert spec.effects == {
        "aero_hinge_load": {"stiffness": 1015.01, "bias": 0.989639},
        "cogging_torque": {"amplitude": 0.0041, "phase": -0.3},
    }


def test_measurements_compared_with_the_default_datasheet_are_said_to_be():
    """phm-workbench without actuator= reads the measurements against its default datasheet: a record of another
    actuator at the same sample rate passes every file check, so the command line is told which one it got."""
    from phm_torch.apps.workbench import default_actuator_note

    note = default_actuator_note(["measurements=my.csv"], "ema_reference")
    assert note is not None and "default datasheet ema_reference" in note and "actuator=<name>" in note
    for given in ("actuator=my_ema", "+actuator=my_ema", "actuator=ema_reference"):
        assert default_actuator_note(["measurements=my.csv", given], "my_ema") is None
    assert default_actuator_note(["actuator.gear_ratio=150"], "ema_reference") is not None  # a field, not a choice


@pytest.mark.slow  # 2-4 min on 2 cores
def test_a_trim_load_sized_by_the_actuator_is_found_fitted_and_explains_the_error():
    """On the 270 V rudder a trim load of 300 N m (an eighth of its stall hinge moment) is hidden. The effect's
    probe, normalisation and bound follow the actuator's size (with the reference-sized ones, 1 N m and a bound
    of 100 N m, the hinge load was not even significant here and a closure was fitted instead). The
    calibration first bends friction and inertia to absorb the load; the chosen candidate's fit is continued
    until it converges, so they come back and the error falls to the noise floor."""
    from hydra.utils import instantiate

    from phm_torch.command import load_command_node

    rudder = load_actuator("ema_hvdc_rudder")
    node = {**load_command_node("chirp_hvdc_rudder")[1], "duration": 0.3}
    hidden = Case({"aero_hinge_load": {"stiffness": 0.0, "bias": 300.0}}, {"current": 0.05, "position": 2e-5}, seed=5)
    m = synthesize(rudder, [hidden], instantiate(node), 0.3)[0]
    wb = Workbench(rudder, settings=quick_settings(rounds=1, refit_top=1))
    res = wb.run([record_from_measurement(m, rudder, ["position", "current"], "trim_load")])
    best = res.candidates[0]
    assert best.effect == "aero_hinge_load" and best.significant, [(c.effect, c.log10_p) for c in res.candidates]
    assert res.added == ["aero_hinge_load"] and res.closure is None
    fitted = res.final.fitted()
    assert fitted["aero_hinge_load.bias"][0] == pytest.approx(300.0, rel=0.01), fitted
    assert fitted["dry_friction"][0] == pytest.approx(1.0, abs=0.05), fitted
    after = res.metrics["model + aero_hinge_load"]
    assert after["nrmse"]["total"] <= 1.1 * after["noise_floor"]["total"], after


def test_closure_output_unit_follows_the_actuator_unless_given():
    from phm_torch.workbench.closure import ClosureSettings, output_scale

    rudder = load_actuator("ema_hvdc_rudder")
    assert output_scale(ClosureSettings(), P) == pytest.approx(1e-3)  # the former fixed unit, on the default
    assert output_scale(ClosureSettings(), rudder) == pytest.approx(5e-3)  # 5 x the peak motor torque
    assert output_scale(ClosureSettings(equation="voltage"), rudder) == pytest.approx(270 / 28000)
    assert output_scale(ClosureSettings(output_scale=2e-3), rudder) == 2e-3
    with pytest.raises(ValueError, match="closure.output_scale"):
        ClosureSettings(output_scale=-1.0)


@pytest.mark.slow  # 2.4 min beside two other jobs
def test_the_lf_models_own_error_on_a_command_is_measured_against_the_noise():
    """fidelity_gap: on a step doublet (the motor at its speed and voltage limits, where the LF model is at its
    worst) the HF model with the calibrated parameters differs from the LF one by more than the record's noise, and
    most at the reversal; on a chirp recorded with a bench's noise it differs by less than that noise."""
    from phm_torch.command import Profile
    from phm_torch.workbench.fidelity_gap import fidelity_gap

    duration = 0.12
    doublet = Profile([0.0, 0.02, 0.02, 0.06, 0.06, duration], [0.0, 0.0, 4e-3, 4e-3, -4e-3, -4e-3], duration)
    settings = quick_settings(calibration=quick_settings().calibration.__class__(max_iter=2))
    noisy = {"current": 0.1, "position": 1e-4}
    found = {}
    for name, command, noise in (("doublet", doublet, NOISE), ("chirp", Chirp(duration=duration), noisy)):
        m = synthesize(P, [Case({}, noise, seed=5)], command, duration, fidelity="hf")[0]
        wb = Workbench(P, settings=settings)
        cal = wb.calibrate(wb.evaluator([record_from_measurement(m, P, ["position", "current"], name)]))
        floor = wb.metrics(cal, cal.sigma)["noise_floor"]["total"]
        found[name] = fidelity_gap(cal, floor)
    assert found["doublet"]["above_floor"] and found["doublet"]["nrmse"]["total"] > 5 * found["doublet"]["noise_floor"]
    assert 0.06 < found["doublet"]["worst_t"][0] < 0.08  # the reversal at 0.06 s
    assert not found["chirp"]["above_floor"] and found["chirp"]["nrmse"]["total"] > 0
    # the doublet drives the motor to its limits, the gentle chirp keeps it far below: the advice says which
    assert max(found["doublet"]["limits"].values()) >= 0.5 and "speed and voltage limits" in found["doublet"]["advice"]
    assert max(found["chirp"]["limits"].values()) < 0.5 and "far from its limits" in found["chirp"]["advice"]
