"""Provenance: artefacts know their actuator and test command; apps adopt them or refuse a mismatch."""

from __future__ import annotations

import json
import math
from pathlib import Path

import pytest
import torch

from phm_torch import provenance
from phm_torch.command import Chirp, time_grid
from phm_torch.online.command_check import NRMSE_TOLERANCE, check_command
from phm_torch.params import CONF_DIR, load_actuator

CHIRP = {"_target_": "phm_torch.command.Chirp", "amplitude": 5e-3, "f_start": 0.0, "f_end": 15.0, "duration": 0.5}


def test_actuator_record_hashes_values_not_spelling(params):
    record = provenance.actuator_record("ema_reference", params)
    again = provenance.actuator_record("renamed", params.replace(gear_ratio=int(params.gear_ratio)))
    assert record["sha256"] == again["sha256"]  # 200 and 200.0 are the same actuator
    other = provenance.actuator_record("ema_reference", params.replace(gear_ratio=params.gear_ratio * 1.01))
    assert other["sha256"] != record["sha256"]  # a 1 % change is another actuator
    assert provenance.validate(record, "actuator", "x") == record
    edited = json.loads(json.dumps(record))
    edited["values"]["gear_ratio"] = 150.0
    with pytest.raises(ValueError, match="does not match its own values"):
        provenance.validate(edited, "actuator", "x")


def test_shipped_configs_are_named_by_their_hash(params):
    record = provenance.actuator_record("?", params)
    assert provenance.known_name("actuator", record["sha256"]) == "ema_reference"
    assert provenance.known_name("command", provenance.command_record("?", CHIRP)["sha256"]) == "chirp"
    assert provenance.known_name("actuator", "0" * 64) is None


def test_reconcile_adopts_or_refuses(params):
    made = provenance.actuator_record("ema_reference", params)
    asked = provenance.actuator_record("my_ema", params.replace(gear_ratio=150.0))
    # nothing explicit: the artefact's actuator is used
    assert provenance.reconcile(made, None, False, "actuator", "store s") == made
    assert provenance.reconcile(made, asked, False, "actuator", "store s") == made
    # the same values under another name are the same actuator
    same = provenance.actuator_record("copy", params)
    assert provenance.reconcile(made, same, True, "actuator", "store s")["sha256"] == made["sha256"]
    # an explicit, different choice is a one-line error naming both
    with pytest.raises(
        ValueError,
        match=r"actuator=my_ema .* differs from the actuator store s was made for: "
        r"ema_reference",
    ):
        provenance.reconcile(made, asked, True, "actuator", "store s")
    # an artefact from before provenance: the request is assumed
    assert provenance.reconcile(None, asked, True, "actuator", "old") == asked


def test_command_check_names_shift_scale_and_other_command():
    fs = 20000.0
    cmd = Chirp(**{k: v for k, v in CHIRP.items() if k != "_target_"})
    t = time_grid(cmd.duration, fs)
    expected = cmd(t)
    same = check_command(
        expected + 1e-6 * torch.randn(t.shape, generator=torch.Generator().manual_seed(0), dtype=t.dtype), expected, fs
    )
    assert same.ok and same.nrmse < 0.01 and math.isclose(same.gain, 1.0, abs_tol=1e-3)
    late = check_command(cmd(t - 0.010), expected, fs)  # a 10 ms trigger offset
    assert not late.ok and late.nrmse > 0.1
    assert late.best_lag_s == pytest.approx(0.010, abs=1.0 / fs)
    assert "best lag 10.0 ms" in late.reason()
    double = check_command(2.0 * expected, expected, fs)  # twice the amplitude
    assert not double.ok and double.gain == pytest.approx(2.0, rel=1e-3)
    other = check_command(Chirp(5e-3, 0.0, 8.0, 0.5)(t), expected, fs)
    assert not other.ok and other.nrmse > NRMSE_TOLERANCE
    with pytest.raises(ValueError, match="samples"):
        check_command(expected[:-1], expected, fs)


@pytest.mark.slow  # a store and a training; ~55 s (the refusal: test_user_config_folder_reaches_every_stage)
def test_train_refuses_a_store_of_another_actuator_and_evaluate_adopts_it(compose, tmp_path):
    """A store made for one actuator: phm-train with another explicit actuator stops before any work;
    without actuator= the bundle records the store's."""
    from phm_torch.apps.generate import generate
    from phm_torch.apps.train import train_surrogates

    data = tmp_path / "data"
    generate(
        compose(
            "generate",
            [
                f"data_dir={data}",
                "actuator.gear_ratio=180.0",
                "dataset.n_train=24",
                "dataset.n_val=8",
                "dataset.n_rul=4",
                "dataset.chunk_size=24",
                "dataset.fidelity=lf",
                "dataset.n_labels=0",
                "assessment.sweep.max_extensions=0",
                "assessment.sweep.refine=0",
                "assessment.sweep.rotor_positions=1",
                "+dataset.healthy_fraction=null",
                "progress=false",
            ],
        )
    )
    manifest = json.loads((data / "manifest.json").read_text())
    assert manifest["provenance"]["actuator"]["values"]["gear_ratio"] == 180.0
    assert manifest["provenance"]["command"]["name"] == "chirp"
    with pytest.raises(ValueError, match=r"actuator=ema_reference .* differs from the actuator store"):
        train_surrogates(compose("train", [f"data_dir={data}", "actuator=ema_reference", f"out_dir={tmp_path}/t"]))
    metrics, objects = train_surrogates(
        compose(
            "train",
            [
                f"data_dir={data}",
                f"out_dir={tmp_path}/t",
                "n_modes=4",
                "n_points=8",
                "selector=qdeim",
                "model.fit.max_epochs=2",
                "classifier_refine.rounds=0",
                "verdict_classifier=false",
                "trainer.enable_progress_bar=false",
            ],
        )
    )
    recorded = objects["bundle"].provenance
    assert recorded["actuator"]["sha256"] == manifest["provenance"]["actuator"]["sha256"]
    # the chosen config's name with the hash of the values actually used (gear ratio 180, not the shipped 200)
    assert metrics["actuator"] == f"ema_reference (sha256 {recorded['actuator']['sha256'][:8]})"
    assert provenance.known_name("actuator", recorded["actuator"]["sha256"]) is None


@pytest.mark.parametrize("app", ["phm_torch.apps.simulate", "phm_torch.apps.train"])
def test_unknown_actuator_lists_the_available_ones(run_cli, app):
    done = run_cli(app, "actuator=no_such_ema", timeout=60)
    assert done.returncode != 0
    assert "Available options in 'actuator'" in done.stderr and "ema_reference" in done.stderr


def test_user_config_folder_reaches_every_stage(run_cli, tmp_path):
    """A user's own actuator and command YAML outside the repository, found through Hydra's search path:
    phm-run passes the choice (and the folder) to its stages, and the store records it. The command is a step
    profile (``Profile``): a test shape that is not a sweep reaches the store the same way."""
    folder = tmp_path / "my_conf"
    (folder / "actuator").mkdir(parents=True)
    (folder / "command").mkdir()
    text = (CONF_DIR / "actuator" / "ema_reference.yaml").read_text()
    (folder / "actuator" / "my_ema.yaml").write_text(text.replace("gear_ratio: 200.0", "gear_ratio: 160.0"))
    (folder / "command" / "my_step.yaml").write_text(
        "_target_: phm_torch.command.Profile\ntimes: [0.0, 0.02, 0.02, 0.1]\npositions: [0.0, 0.0, 4.0e-3, 4.0e-3]\n"
        "duration: 0.1\n"
    )
    done = run_cli(
        "phm_torch.apps.run",
        "actuator=my_ema",
        "command=my_step",
        f"hydra.searchpath=[file://{folder}]",
        f"out_dir={tmp_path}/run",
        "stages=[generate]",
        'generate=["dataset.n_train=8","dataset.n_val=4","dataset.n_rul=2","dataset.chunk_size=8",'
        '"dataset.fidelity=lf","dataset.n_labels=0","+dataset.healthy_fraction=null","progress=false",'
        '"assessment.sweep.max_extensions=0","assessment.sweep.refine=0","assessment.sweep.rotor_positions=1",'
        '"assessment.sweep.frequencies=[15,30,60,90,130]","assessment.sweep.cycles=3"]',  # a short sweep
        timeout=300,
    )
    assert done.returncode == 0, done.stderr[-2000:]
    manifest = json.loads((Path(tmp_path) / "run" / "data" / "manifest.json").read_text())
    actuator, command = manifest["provenance"]["actuator"], manifest["provenance"]["command"]
    assert actuator["name"] == "my_ema" and actuator["values"]["gear_ratio"] == 160.0
    assert (
        actuator["sha256"]
        == provenance.actuator_record("x", load_actuator(str(folder / "actuator" / "my_ema.yaml")))["sha256"]
    )
    assert command["name"] == "my_step" and command["params"]["times"] == [0.0, 0.02, 0.02, 0.1]
    # a consumer told another actuator explicitly refuses, naming both
    refused = run_cli("phm_torch.apps.train", f"data_dir={tmp_path}/run/data", "actuator=ema_reference", timeout=120)
    assert refused.returncode == 2
    assert "differs from the actuator" in refused.stderr and "my_ema" in refused.stderr


def test_workbench_records_the_command_and_checks_the_files_against_it(compose):
    from phm_torch.apps.workbench import build_workbench, command_provenance

    demo = str(Path(__file__).resolve().parent.parent / "examples" / "workbench_hidden_cogging.csv")
    cfg = compose("workbench", [f"measurements={demo}", "command=chirp"])
    records = build_workbench(cfg).load(demo)
    assert command_provenance(cfg, records)["name"] == "chirp"
    assert command_provenance(compose("workbench", [f"measurements={demo}"]), records)["name"] == "measured"
    with pytest.raises(ValueError, match=r"command=sine: .*workbench_hidden_cogging.csv: command differs"):
        command_provenance(compose("workbench", [f"measurements={demo}", "command=sine"]), records)


def test_workbench_refuses_a_measurement_recorded_on_another_actuator(compose, tmp_path):
    """The shipped demo's sidecar says it was recorded on ema_reference: compared with the rudder's datasheet it
    passed every file check and the report blamed missing physics (a closure was fitted); now it is an error
    naming both. Its own actuator, chosen or default, passes, and a file without a sidecar is not checked."""
    from phm_torch.apps.workbench import build_workbench, check_recorded_actuator

    demo = Path(__file__).resolve().parent.parent / "examples" / "workbench_hidden_cogging.csv"
    cfg = compose("workbench", [f"measurements={demo}", "actuator=ema_hvdc_rudder"])
    records = build_workbench(cfg).load(str(demo))
    with pytest.raises(
        ValueError,
        match=r"actuator=ema_hvdc_rudder .* differs from the actuator measurement .*"
        r"workbench_hidden_cogging.csv was made for: ema_reference",
    ):
        check_recorded_actuator(cfg, records)
    for overrides in ([], ["actuator=ema_reference"]):
        check_recorded_actuator(compose("workbench", [f"measurements={demo}", *overrides]), records)
    bare = tmp_path / "bare.csv"
    bare.write_bytes(demo.read_bytes())  # no sidecar: nothing recorded to check
    check_recorded_actuator(cfg, build_workbench(cfg).load(str(bare)))


def test_a_slewed_chirp_is_the_chirp_on_a_ramp_and_hashes_apart_from_it():
    """SlewedChirp = Chirp + r t on the acquisition grid; its record (class included) never matches a plain chirp's,
    and a bad slew rate is refused by name."""
    from phm_torch.command import COMMANDS, SlewedChirp, with_defaults

    t = time_grid(0.5, 20_000.0)
    slewed = SlewedChirp(5e-3, 0.0, 15.0, 0.5, slew_rate=0.02)
    assert torch.allclose(slewed(t), Chirp()(t) + 0.02 * t, atol=1e-15, rtol=0)
    assert COMMANDS["slewed_chirp"] is SlewedChirp
    node = with_defaults({**CHIRP, "_target_": "phm_torch.command.SlewedChirp", "slew_rate": 0.02})
    assert provenance.command_record("s", node)["sha256"] != provenance.command_record("c", CHIRP)["sha256"]
    with pytest.raises(ValueError, match="command.slew_rate must be finite"):
        SlewedChirp(5e-3, 0.0, 15.0, 0.5, slew_rate=float("inf"))
    with pytest.raises(ValueError, match="command.amplitude must be > 0"):
        SlewedChirp(0.0, 0.0, 15.0, 0.5, slew_rate=0.0)


def test_a_log_chirp_sweeps_each_octave_in_equal_time_and_hashes_apart(tmp_path):
    """LogChirp: instantaneous frequency f0 (f1/f0)^(t/T) (from the phase's slope), bad sweeps refused by name, a
    user's YAML read as any command file, and its record never a linear chirp's."""
    from phm_torch.command import COMMANDS, LogChirp, load_command_node

    sweep = LogChirp(5e-3, 1.0, 16.0, 0.8)
    t = time_grid(0.8, 20_000.0)
    # the phase is the integral of the instantaneous frequency f0 (f1/f0)^(t/T): 2, 4, 8 Hz at 0.2, 0.4, 0.6 s
    f = 1.0 * 16.0 ** (t / 0.8)
    phase = torch.cat([torch.zeros(1, dtype=t.dtype), torch.cumulative_trapezoid(f, t)])
    torch.testing.assert_close(sweep(t), 5e-3 * torch.sin(2 * torch.pi * phase), atol=1e-9, rtol=0)
    assert COMMANDS["log_chirp"] is LogChirp
    for f0, f1 in ((0.0, 15.0), (5.0, 5.0), (5.0, 0.0)):
        with pytest.raises(ValueError, match="a log chirp needs f_start > 0"):
            LogChirp(5e-3, f0, f1, 0.5)
    with pytest.raises(ValueError, match="command frequencies must be >= 0"):
        LogChirp(5e-3, -1.0, 5.0, 0.5)
    path = tmp_path / "my_sweep.yaml"
    path.write_text(
        "_target_: phm_torch.command.LogChirp\namplitude: 5.0e-3\nf_start: 1.0\nf_end: 16.0\nduration: 0.8\n"
    )
    name, node = load_command_node(str(path))
    assert name == str(path) and node["f_end"] == 16.0
    linear = {**node, "_target_": "phm_torch.command.Chirp"}
    assert provenance.command_record("s", node)["sha256"] != provenance.command_record("s", linear)["sha256"]


def test_a_profile_steps_ramps_and_holds_through_its_breakpoints(tmp_path):
    """Profile: linear between breakpoints, a step at two equal times (the later position from that time on), the
    first position held before and the last after; amplitude the largest |position|; bad profiles refused by field;
    a user's YAML read as any command file, and a moved breakpoint a different command."""
    from hydra.utils import instantiate

    from phm_torch.command import COMMANDS, Profile, load_command_node

    doublet = Profile([0.0, 0.1, 0.1, 0.3, 0.4], [1e-3, 1e-3, 4e-3, 4e-3, -2e-3], 0.5)
    t = torch.tensor([0.0, 0.0999, 0.1, 0.2, 0.3, 0.35, 0.4, 0.5], dtype=torch.float64)
    want = [1e-3, 1e-3, 4e-3, 4e-3, 4e-3, 1e-3, -2e-3, -2e-3]
    torch.testing.assert_close(doublet(t), torch.tensor(want, dtype=torch.float64), atol=1e-12, rtol=0)
    late = Profile([0.05, 0.15], [0.0, 2e-3], 0.2)  # the first position held from t = 0
    torch.testing.assert_close(late(torch.tensor([0.0, 0.1, 0.2])), torch.tensor([0.0, 1e-3, 2e-3]))
    assert doublet.amplitude == 4e-3 and COMMANDS["profile"] is Profile
    bad = {
        "times must be >= 0 and non-decreasing": ([0.0, 0.2, 0.1], [0.0, 1e-3, 0.0]),
        "at most two breakpoints at one time": ([0.0, 0.1, 0.1, 0.1], [0.0, 1e-3, 0.0, 1e-3]),
        "as many positions as times": ([0.0, 0.1], [0.0, 1e-3, 0.0]),
        "never leaves 0": ([0.0, 0.1], [0.0, 0.0]),
        "positions must be a list of numbers": ([0.0, 0.1], ["a", 1e-3]),
        "times must hold finite numbers": ([0.0, float("nan")], [0.0, 1e-3]),
    }
    for message, (times, positions) in bad.items():
        with pytest.raises(ValueError, match=message):
            Profile(times, positions, 0.5)
    with pytest.raises(ValueError, match="command.duration must be > 0"):
        Profile([0.0, 0.1], [0.0, 1e-3], 0.0)
    path = tmp_path / "doublet.yaml"
    path.write_text(
        "_target_: phm_torch.command.Profile\ntimes: [0.0, 0.1, 0.1, 0.5]\npositions: [0.0, 0.0, 2.0e-3, 2.0e-3]\n"
        "duration: 0.5\n"
    )
    name, node = load_command_node(str(path))
    assert instantiate(node)(torch.tensor([0.05, 0.1], dtype=torch.float64)).tolist() == [0.0, 2e-3]
    moved = {**node, "times": [0.0, 0.12, 0.12, 0.5]}
    assert provenance.command_record(name, node)["sha256"] != provenance.command_record(name, moved)["sha256"]


def test_a_multisine_sums_its_lines_and_reads_them_back():
    """Multisine: the record's DFT reads each line's amplitude and phase (whole cycles of every line in the record);
    the amplitude is the lines' summed peak; mismatched or non-positive lines refused by field."""
    from phm_torch.command import COMMANDS, Multisine

    lines = Multisine([2e-3, 1e-3, 5e-4], [2.0, 6.0, 14.0], 0.5, phases=[0.0, 1.0, -2.0])
    t = time_grid(0.5, 20_000.0)[:-1]  # 10,000 samples: whole cycles of 2, 6 and 14 Hz
    spectrum = torch.fft.rfft(lines(t)) * 2 / t.numel()
    for a, f, phi in zip(lines.amplitudes, lines.frequencies, lines.phases, strict=True):
        line = spectrum[round(f * 0.5)]  # bin spacing 2 Hz
        want = a * complex(math.cos(phi - math.pi / 2), math.sin(phi - math.pi / 2))  # sin = cos(. - pi/2)
        assert abs(complex(line) - want) < 1e-9 * a
    assert lines.amplitude == pytest.approx(3.5e-3) and COMMANDS["multisine"] is Multisine
    assert Multisine([1e-3], [3.0], 0.5).phases == (0.0,)
    with pytest.raises(ValueError, match="as many frequencies"):
        Multisine([1e-3, 1e-3], [3.0], 0.5)
    with pytest.raises(ValueError, match="must be > 0"):
        Multisine([1e-3], [0.0], 0.5)
