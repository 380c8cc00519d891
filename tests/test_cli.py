"""Command-line apps: ``phm-simulate`` (subprocess and in-process) and the ``phm-cases`` job at tiny scale.

The subprocess runs (each pays the torch/Hydra import, ~4 s) are started together in one module fixture.
"""

from __future__ import annotations

import json
import subprocess
from importlib import metadata
from pathlib import Path

import numpy as np
import pytest

from phm_torch.apps.cases import parse_cases, run_cases
from phm_torch.apps.simulate import simulate_to_csv
from phm_torch.io import read_measurement

SIM = "phm_torch.apps.simulate"
QUICK = ("fidelity=lf", "command.duration=0.05")
NOISY = ("seed=7", "noise.current=0.05", "noise.position=1e-5")
LF_COLUMNS = ["time", "command", "position", "current", "speed", "motor_angle"]

CLI_RUNS = {
    "noisy_a": (*QUICK, *NOISY, "out=noisy_a.csv"),
    "noisy_b": (*QUICK, *NOISY, "out=sub/noisy_b.csv"),
    "bad_fault": (*QUICK, "faults=[0,0,1.5,0,0,0,0.5,0.5]", "out=x.csv"),
    "bad_effect": (*QUICK, "+effects.no_such_effect={}", "out=x.csv"),
}


@pytest.fixture(scope="module")
def cli(tmp_path_factory, spawn_cli) -> tuple[Path, dict[str, subprocess.CompletedProcess]]:
    """Every subprocess run of CLI_RUNS, in parallel; (working directory, {name: completed process})."""
    cwd = tmp_path_factory.mktemp("cli")
    procs = {name: spawn_cli(SIM, args, cwd) for name, args in CLI_RUNS.items()}
    done = {}
    for name, proc in procs.items():
        out, err = proc.communicate(timeout=180)
        done[name] = subprocess.CompletedProcess(proc.args, proc.returncode, out, err)
    return cwd, done


@pytest.fixture(scope="module")
def clean(tmp_path_factory, compose) -> dict[str, np.ndarray]:
    """The same LF run as the CLI runs, noise-free, in process: {channel: (n,)}."""
    out = tmp_path_factory.mktemp("clean") / "clean.csv"
    _, objects = simulate_to_csv(compose("simulate", [*QUICK, f"out={out}", "plot=false"]))
    return {k: v[0].numpy() for k, v in objects["signals"].channels.items()}


def test_cli_writes_csv_png_and_metrics(cli, clean):
    cwd, runs = cli
    run = runs["noisy_a"]
    assert run.returncode == 0, run.stderr
    csv = cwd / "noisy_a.csv"
    assert csv.read_text().splitlines()[0].split(",") == LF_COLUMNS
    m = read_measurement(csv, expected_rate=20000.0)
    assert len(m) == 1001  # 0.05 s at 20 kHz, both ends
    assert m.time[-1] == pytest.approx(0.05)
    assert (cwd / "noisy_a.png").stat().st_size > 10_000
    metrics = json.loads(run.stdout[run.stdout.index("{") :])
    err = clean["command"] - clean["position"]  # metrics describe the noise-free simulation
    assert metrics["tracking_error_rms"] == pytest.approx(float(np.sqrt(np.mean(err**2))), rel=1e-9)
    assert metrics["peak_current"] == pytest.approx(float(np.abs(clean["current"]).max()), rel=1e-9)
    assert metrics["samples"] == 1001 and metrics["fidelity"] == "lf" and metrics["seed"] == 7
    assert len(list(cwd.glob("hydra/*/.hydra/config.yaml"))) == len(CLI_RUNS)


def test_cli_seed_reproducible_with_noise(cli, clean):
    cwd, runs = cli
    assert runs["noisy_a"].returncode == 0, runs["noisy_a"].stderr
    assert runs["noisy_b"].returncode == 0, runs["noisy_b"].stderr
    a, b = read_measurement(cwd / "noisy_a.csv"), read_measurement(cwd / "sub" / "noisy_b.csv")
    for name in ("current", "position", "command", "speed"):
        np.testing.assert_array_equal(a[name], b[name])
    np.testing.assert_array_equal(a.command, clean["command"])
    np.testing.assert_array_equal(a["speed"], clean["speed"])  # noise only on current and position
    assert np.std(a.current - clean["current"]) == pytest.approx(0.05, rel=0.15)
    assert np.std(a.position - clean["position"]) == pytest.approx(1e-5, rel=0.15)


@pytest.mark.parametrize(
    ("name", "field"),
    [
        ("bad_fault", "faults[2] (k3, short_a) = 1.5 is outside [0, 1]"),
        ("bad_effect", "effects: unknown effect 'no_such_effect'"),
    ],
)
def test_cli_bad_input_exits_nonzero_with_message(cli, name, field):
    cwd, runs = cli
    run = runs[name]
    assert run.returncode != 0
    assert field in run.stderr + run.stdout
    assert "Traceback" not in run.stderr
    assert not (cwd / "x.csv").exists()


# ---- in-process: the same function the CLI calls ----------------------------------------------------
def test_hf_csv_has_phase_currents(compose, tmp_path):
    cfg = compose("simulate", ["command.duration=0.005", f"out={tmp_path / 'hf.csv'}", "plot=false"])
    assert cfg.fidelity == "hf" and list(cfg.faults) == [0, 0, 0, 0, 0, 0, 0.5, 0.5]
    metrics, objects = simulate_to_csv(cfg)
    header = (tmp_path / "hf.csv").read_text().splitlines()[0].split(",")
    assert header == [*LF_COLUMNS, "ia", "ib", "ic"]
    assert len(read_measurement(tmp_path / "hf.csv")) == 101
    assert metrics["plot"] is None and not (tmp_path / "hf.png").exists()
    assert objects["signals"].fidelity == "hf"


def test_effects_and_seed_change_output(compose, tmp_path):
    base = ["fidelity=lf", "command.duration=0.02", "plot=false", "noise.current=0.01"]
    _, s1 = simulate_to_csv(compose("simulate", [*base, "seed=1", f"out={tmp_path / 'a.csv'}"]))
    _, s2 = simulate_to_csv(compose("simulate", [*base, "seed=2", f"out={tmp_path / 'b.csv'}"]))
    assert not np.array_equal(s1["channels"]["current"], s2["channels"]["current"])
    np.testing.assert_array_equal(s1["signals"]["current"], s2["signals"]["current"])  # noise-free part
    metrics, s3 = simulate_to_csv(
        compose("simulate", [*base, "seed=1", "+effects.stribeck_friction={}", f"out={tmp_path / 'c.csv'}"])
    )
    assert metrics["effects"] == ["stribeck_friction"]
    assert len(s3["signals"].meta["effects"]) == 1


@pytest.mark.parametrize(
    ("overrides", "message"),
    [
        (["faults=[0,0,0]"], "faults must have 8 entries"),
        (["faults=[nan,0,0,0,0,0,0.5,0.5]"], "faults[0] (k1, dry_friction) is not finite"),
        (["faults=[0,0,0,0,0,0,0.5,-0.1]"], "faults[7] (k8, gain_drift) = -0.1 is outside [0, 1]"),
        (["faults=[0,0,0,0,0,0,0.5,x]"], "faults[7] (k8, gain_drift) must be a number"),
        (["noise.position=-1e-5"], "noise.position must be >= 0"),
        (["noise.current=abc"], "noise.current must be a number"),
        (["+effects.no_such_effect={}"], "effects: unknown effect 'no_such_effect'"),
        (["+effects.stribeck_friction=3"], "effects.stribeck_friction must be a mapping"),
        (["fidelity=mf"], "fidelity must be one of"),
        (["seed=-1"], "seed must be >= 0"),
        (["seed=1.5"], "seed must be an integer"),
        (["command.amplitude=-1"], "command: command.amplitude must be > 0"),
        (["out=result.txt"], "out must end in .csv"),
        (["actuator.phase_resistance=-1"], "actuator.phase_resistance must be > 0"),
    ],
)
def test_bad_config_names_the_field(compose, tmp_path, overrides, message):
    out = [f"out={tmp_path / 'x.csv'}"] if not any(o.startswith("out=") for o in overrides) else []
    cfg = compose("simulate", ["fidelity=lf", "command.duration=0.01", *out, *overrides])
    with pytest.raises(ValueError) as info:
        simulate_to_csv(cfg)
    assert message in str(info.value)
    assert not (tmp_path / "x.csv").exists()


# ---- phm-cases --------------------------------------------------------------------------------------
def test_run_job_tiny(compose, tmp_path):
    out = tmp_path / "run"
    cfg = compose("cases", ["fidelity=lf", "command.duration=0.02", f"out_dir={out}"])
    metrics, objects = run_cases(cfg)
    names = list(cfg.cases)
    assert objects["names"] == ["nominal", *names] and len(names) == 8
    assert objects["signals"].channels["current"].shape == (9, 401)  # one batched call
    saved = json.loads((out / "metrics.json").read_text())
    assert saved == json.loads(json.dumps(metrics))
    assert list(saved["cases"]) == names and "nominal_faults" not in saved
    for name, case in saved["cases"].items():
        assert 0.0 <= case["nrmse_current"] < 1.0 and 0.0 <= case["nrmse_position"] < 1.0, name
        assert (out / case["csv"]).is_file() and (out / case["plot"]).is_file()
        assert len(read_measurement(out / case["csv"], expected_rate=20000.0)) == 401
    assert saved["cases"]["k1_friction"]["faults"] == [0.5, 0, 0, 0, 0, 0, 0.5, 0.5]
    assert saved["cases"]["k8_gain_drift"]["nrmse_position"] > 0
    assert (out / "nominal.csv").is_file() and "nrmse_current" not in saved["nominal"]


def test_run_job_custom_cases(compose, tmp_path):
    cfg = compose(
        "cases",
        [
            "fidelity=lf",
            "command.duration=0.01",
            f"out_dir={tmp_path}",
            "plot=false",
            "~cases",
            "+cases={heavy: {k1: 1.0, k2: 1.0}, full: [0,0,0,0.2,0,0,0.5,0.5]}",
        ],
    )
    metrics, _ = run_cases(cfg)
    assert list(metrics["cases"]) == ["heavy", "full"]
    assert metrics["cases"]["heavy"]["faults"] == [1.0, 1.0, 0, 0, 0, 0, 0.5, 0.5]
    assert metrics["cases"]["full"]["faults"][3] == 0.2
    assert metrics["cases"]["heavy"]["nrmse_current"] > 0
    assert not list(tmp_path.glob("*.png"))
    cfg = compose(
        "cases",
        [
            "fidelity=lf",
            "command.duration=0.01",
            f"out_dir={tmp_path / 'sub'}",
            "plot=false",
            "only=[k8_gain_drift,k2_backlash]",
            "+cases.extra={k1: 0.1}",
        ],
    )
    metrics, _ = run_cases(cfg)
    assert list(metrics["cases"]) == ["k2_backlash", "k8_gain_drift"]


@pytest.mark.parametrize(
    ("cases", "message"),
    [
        ({"nominal": {"k1": 0.5}}, "invalid case name 'nominal'"),
        ({"a/b": {"k1": 0.5}}, "invalid case name 'a/b'"),
        ({"c": {"k9": 0.5}}, "cases.c: unknown fault 'k9'"),
        ({"c": {"k2": 1.5}}, "cases.c[1] (k2, backlash) = 1.5 is outside [0, 1]"),
        ({"c": [0, 0]}, "cases.c must have 8 entries"),
        ({"c": {}}, "cases.c must be a non-empty mapping"),
    ],
)
def test_run_cases_validation(cases, message):
    with pytest.raises(ValueError) as info:
        parse_cases(cases, [0, 0, 0, 0, 0, 0, 0.5, 0.5])
    assert message in str(info.value)


def test_run_only_unknown_case():
    with pytest.raises(ValueError, match=r"only: unknown case\(s\) \['k9'\]"):
        parse_cases({"a": {"k1": 0.5}}, [0, 0, 0, 0, 0, 0, 0.5, 0.5], only=["k9"])


def test_console_scripts_registered():
    try:
        eps = {ep.name: ep.value for ep in metadata.entry_points(group="console_scripts")}
    except metadata.PackageNotFoundError:  # pragma: no cover
        eps = {}
    if "phm-simulate" not in eps:
        pytest.skip("phm_torch is not pip-installed (pip install -e .)")
    assert eps["phm-simulate"] == "phm_torch.apps.simulate:main"
    assert eps["phm-cases"] == "phm_torch.apps.cases:main"
