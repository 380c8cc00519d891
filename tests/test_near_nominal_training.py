"""The near-nominal FDI's training as a library function (phm_torch/tracking/near_nominal_training.py) and phm-run's
companions stage around it (phm_torch/apps/run_companions.py): settings checked by name, a store split read where
it is near nominal, the stale companions of a replaced pipeline removed, bad stage settings refused."""

from __future__ import annotations

from types import SimpleNamespace

import h5py
import numpy as np
import pytest
import torch
from test_fit_near_nominal_script import life_split
from test_tracking import N_FULL, damage_config, make_pipeline

from phm_torch.apps.run import compose_stage
from phm_torch.apps.run_companions import (
    LATE_WEIGHT,
    RULES,
    choose_end_of_life_rule,
    companion_paths,
    remove_stale,
    run_companions,
)
from phm_torch.apps.track import auto_rule
from phm_torch.faults import FAULT_NAMES
from phm_torch.online.export import export_torchscript
from phm_torch.tracking.companions import companion
from phm_torch.tracking.near_nominal import NearNominalFDI, TooFewNearNominalRecords
from phm_torch.tracking.near_nominal_training import NearNominalTraining, store_records, train_near_nominal
from phm_torch.tracking.tracker_check import TrackerCheck


@pytest.mark.parametrize(
    ("field", "value"),
    [
        ("width_factor", 0.8),
        ("holdout", 1),
        ("steps", 0),
        ("gate", 0.0),
        ("max_damage", 1.5),
        ("noise_levels", (0.02, 0.01)),
        ("full_record", -1),
    ],
)
def test_settings_out_of_range_are_refused_by_name(field, value):
    with pytest.raises(ValueError, match=f"{field} = "):
        NearNominalTraining(**{field: value})


@pytest.fixture(scope="module")
def exported(tmp_path_factory):
    root = tmp_path_factory.mktemp("near_training")
    pipe = make_pipeline()
    export_torchscript(pipe, root / "online.pt", {"damage": damage_config()})
    life_split(root / "life", pipe, n_actuators=10, n_inspections=10)  # 20 held-out records calibrate
    return root, pipe


@pytest.mark.torchscript
def test_the_library_trains_a_network_that_belongs_to_its_pipeline_and_beats_the_spread(exported):
    root, pipe = exported
    settings = NearNominalTraining(full_record=8, steps=3000, gate=1.0, noise_levels=(0.01, 0.02), seed=3)
    net, report = train_near_nominal(root / "online.pt", root / "life", settings)
    assert report is net.provenance and report["calibration_actuators"] == 2 and report["life_records"] == 80
    assert report["width_factor"] == 1.25 and report["store"] is None and report["store_records"] == 0
    assert net.n_full == N_FULL and net.n_modes == 8
    # a pipeline exported without identifiability: the gate reads every damage
    assert report["gate_components"] == [n for n in FAULT_NAMES if n != "eccentricity_phase"]
    rms = torch.tensor([report["heldout"]["0.01"]["rms"][n] for n in ("dry_friction", "backlash", "short_a")])
    assert float(rms.max()) < 0.75 * 0.2 / 12**0.5, rms  # below the truth's own spread (uniform on [0, 0.2])
    net.save(root / "online.near_nominal.pt")
    read = companion("near_nominal", "auto", root / "online.pt", pipe)  # phm-track's auto finds it and checks it
    assert isinstance(read, NearNominalFDI) and read.provenance["steps"] == 3000


@pytest.mark.torchscript
def test_the_gate_skips_what_the_pipeline_does_not_identify(exported, tmp_path):
    _, pipe = exported
    r2 = dict.fromkeys(FAULT_NAMES, 0.9) | {"eccentricity": 0.05, "eccentricity_phase": 0.0, "gain_drift": 0.1}
    export_torchscript(pipe, tmp_path / "online.pt", {"damage": damage_config(), "identifiability": r2})
    life_split(tmp_path / "life", pipe, n_actuators=10, n_inspections=10)
    settings = NearNominalTraining(full_record=8, steps=20, gate=1.0, noise_levels=(0.01, 0.02))
    net, report = train_near_nominal(tmp_path / "online.pt", tmp_path / "life", settings)
    assert report["gate_components"] == ["dry_friction", "backlash", "short_a", "short_b", "short_c"]
    assert net.gate_components_.tolist() == [True] * 5 + [False] * 3


def test_a_store_split_is_read_where_every_damage_is_near_nominal(tmp_path):
    k = np.tile(np.array([0.0] * 6 + [0.5, 0.5]), (5, 1))
    k[1, 0], k[2, 6], k[3, 7] = 0.5, 0.9, 0.95  # a large damage; an eccentricity phase (not a damage); a gain drift
    current = np.arange(5 * 11, dtype=np.float32).reshape(5, 11)
    with h5py.File(tmp_path / "dataset.h5", "w") as f:
        f.create_dataset("train/K", data=k)
        f.create_dataset("train/current", data=current)
    samples, scale, kept = store_records(tmp_path, slice(None), np.array([0.0] * 6 + [0.5, 0.5]), 0.2)
    assert samples.shape == (3, 11) and np.array_equal(kept, k[[0, 2, 4]])
    np.testing.assert_allclose(scale, np.sqrt((current[[0, 2, 4]].astype(np.float64) ** 2).mean(1)))
    with pytest.raises(ValueError, match="store_split: 'rul' is not a split"):
        store_records(tmp_path, slice(None), np.zeros(8), 0.2, "rul")
    with pytest.raises(ValueError, match="store: no dataset.h5"):
        store_records(tmp_path / "none", slice(None), np.zeros(8), 0.2)


@pytest.mark.torchscript
def test_a_life_split_that_leaves_nothing_to_train_on_is_refused(exported, tmp_path):
    root, pipe = exported
    life_split(tmp_path / "life", pipe, n_actuators=1, n_inspections=2)
    with pytest.raises(TooFewNearNominalRecords, match="leave none to train on"):
        train_near_nominal(root / "online.pt", tmp_path / "life", NearNominalTraining(steps=10))
    with pytest.raises(ValueError, match="no truth.json"):
        train_near_nominal(root / "online.pt", tmp_path, NearNominalTraining(steps=10))


def test_the_companions_of_a_replaced_pipeline_are_removed(tmp_path):
    pipeline = tmp_path / "online.pt"
    paths = companion_paths(pipeline)
    assert {p.name for p in paths.values()} == {
        "online.fdi_response.json",
        "online.near_nominal.pt",
        "online.tracker_check.json",
    }
    for path in paths.values():
        path.write_text("x")
    (tmp_path / "other.near_nominal.pt").write_text("x")
    assert sorted(remove_stale(pipeline)) == sorted(str(p) for p in paths.values())
    assert [p.name for p in tmp_path.iterdir()] == ["other.near_nominal.pt"]
    assert remove_stale(pipeline) == []


@pytest.mark.parametrize(
    ("override", "message"),
    [
        ("companions.life_actuators=3", "companions.life_actuators must be >= 5"),
        ("+companions.near_nominal.layers=3", "companions.near_nominal: .*layers"),
        ("companions.near_nominal.holdout=1", "holdout = 1"),
        ("companions.near_nominal.width_factor=0.5", "width_factor = 0.5"),
        ("companions.late_weight=-1", "companions.late_weight must be >= 0"),
    ],
)
def test_bad_companion_settings_are_refused_before_any_work(tmp_path, override, message):
    cfg = compose_stage("run", [f"out_dir={tmp_path}", override])
    with pytest.raises(ValueError, match=message):
        run_companions(cfg, tmp_path, tmp_path / "data", tmp_path / "online.pt", [], [], [])
    assert not (tmp_path / "companions").exists()


def test_too_few_near_nominal_histories_skip_the_near_nominal_fdi_not_the_run(tmp_path, monkeypatch, caplog):
    """A robust actuator's histories leave nominal early: a 28 V ball screw's 40 gave 6 held-out records within the
    gate, 20 needed, and phm-run stopped at the companions stage. The stage now writes no near-nominal FDI, says
    why and which setting gives more, and the run goes on (the tracker reads the pipeline's k_hat there)."""
    import phm_torch.apps.generate as generate_app
    import phm_torch.apps.run_companions as stage
    import phm_torch.apps.track as track_app

    pipeline = tmp_path / "online.pt"
    pipeline.write_text("x")

    def fake_generate(cfg):
        life = tmp_path / "companions" / "data" / "life"
        life.mkdir(parents=True)
        (life / "index.csv").write_text("actuator,hours,file\nA000,0.0,A000/0000.csv\n")
        (life / "A000").mkdir()
        (life / "A000" / "0000.csv").write_text("time,current\n0.0,0.0\n")
        return {"life": {"n_actuators": 5}}, None

    def too_few(*args, **kwargs):
        raise TooFewNearNominalRecords("near-nominal FDI: 6 held-out records within the gate, 20 needed")

    tracked = []

    def fake_track(cfg):  # the ball screw's figures with the record rule (measured: coverage 41 %, all early)
        tracked.append(cfg)
        figures = {"coverage_5_95": 0.41, "eol_intervals_late": 0.0}
        if cfg.verdict == "posterior" and cfg.faulty_at == "p5":  # in time, 5 % early by a little
            figures |= {
                "eol_flagged_early": 0.05,
                "eol_flagged_within_one_inspection": 0.9,
                "eol_intervals_early": 0.02,
            }
        elif cfg.verdict == "posterior":  # 30 % late, a whole interval each
            figures |= {"eol_flagged_early": 0.0, "eol_flagged_within_one_inspection": 0.7, "eol_intervals_late": 0.3}
        else:
            figures |= {"eol_flagged_early": 1.0, "eol_flagged_within_one_inspection": 0.0, "eol_intervals_early": 4.0}
        return {"inspections": 1, "actuators": 1, "tracker": figures}, None

    monkeypatch.setattr(generate_app, "generate", fake_generate)
    monkeypatch.setattr(track_app, "track", fake_track)
    monkeypatch.setattr(stage, "train_near_nominal", too_few)
    provenance = {
        "actuator": {"name": "lin28", "sha256": "faf2dde17f"},
        "command": {"name": "chirp_lin28", "sha256": "a7"},
    }
    loaded = SimpleNamespace(module=None, metadata={"provenance": provenance})
    monkeypatch.setattr(stage, "load_pipeline", lambda path: loaded)
    monkeypatch.setattr(stage, "probe_k_hat", lambda model: [0.0] * 8)
    cfg = compose_stage("run", [f"out_dir={tmp_path}"])
    with caplog.at_level("WARNING"):
        got = run_companions(cfg, tmp_path, tmp_path / "data", pipeline, [], [], [])
    assert got["near_nominal"] is None
    assert "6 held-out records within the gate" in got["near_nominal_skipped"]
    assert got["response"] is None and got["life_inspections"] == 1  # one inspection: too few for a response too
    assert "no near-nominal FDI written" in caplog.text and "companions.life_actuators=" in caplog.text
    assert not companion_paths(pipeline)["near_nominal"].exists()
    # the tracker as phm-track will run it (no near-nominal FDI) measured on these histories under each end-of-life
    # rule, the rule chosen as with one, its figures written beside the pipeline (where phm-track's auto reads the
    # rule) and their shortfall said
    runs = [(c.verdict, c.faulty_at, c.near_nominal) for c in tracked[1:]]
    assert runs == [(v, f, None) for v, f in RULES]
    assert (got["tracker_rule"]["verdict"], got["tracker_rule"]["faulty_at"]) == ("posterior", "p5")
    check = TrackerCheck.load(companion_paths(pipeline)["tracker_check"])
    assert check.figures["coverage_5_95"] == 0.41 and check.rule == {"verdict": "posterior", "faulty_at": "p5"}
    assert check.pipeline["actuator"] == "lin28 (sha256 faf2dde1)" and check.pipeline["command"].startswith(
        "chirp_lin28"
    )
    assert got["tracker_check_figures"]["eol_flagged_early"] == 0.05
    assert "held the true RUL on 41 % of the inspections" in caplog.text
    assert auto_rule(None, check=check) == {"verdict": "posterior", "faulty_at": "p5"}


def test_the_stage_needs_the_evaluate_stage_pipeline(tmp_path):
    cfg = compose_stage("run", [f"out_dir={tmp_path}"])
    with pytest.raises(ValueError, match="companions needs the evaluate stage's pipeline"):
        run_companions(cfg, tmp_path, tmp_path / "data", tmp_path / "online.pt", [], [], [])


def _tracked(figures: dict[tuple[str, str], tuple[float | None, float]]) -> dict:
    return {
        rule: {"tracker": {"eol_intervals_early": early, "eol_intervals_late": late, "eol_flagged_early": 0.1}}
        for rule, (early, late) in figures.items()
    }


# (mean intervals flagged early, late) per rule of RULES, in its order: record/p50, record/p5, posterior/p50,
# posterior/p5; the cost is early + LATE_WEIGHT (5) x late
CASES = [
    # the ball-screw sketch at its default store (measured, 40 histories): record flags 62 % of the lives early by up to
    # 21 intervals, posterior/p5 15 % late by at most a quarter of one, posterior/p50 one life never
    ([(5.249, 0.001), (5.249, 0.001), (0.0, 0.132), (0.0, 0.012)], ("posterior", "p5")),
    # a tie keeps the earlier rule (the default first)
    ([(0.01, 0.0), (0.01, 0.0), (0.0, 0.05), (0.02, 0.01)], ("record", "p50")),
    # late weighs more: one interval early on every life beats 0.3 late (cost 1.5)
    ([(1.0, 0.0), (1.2, 0.0), (0.0, 0.3), (0.5, 0.2)], ("record", "p50")),
    # a rule without its figures is not scored
    ([(None, 0.0), (0.3, 0.6), (0.2, 0.7), (0.1, 0.85)], ("record", "p5")),
]


@pytest.mark.parametrize(("figures", "chosen"), CASES)
def test_the_end_of_life_rule_flags_least_far_out_late_weighing_more(figures, chosen):
    verdict = choose_end_of_life_rule(_tracked(dict(zip(RULES, figures))))
    assert (verdict["verdict"], verdict["faulty_at"]) == chosen
    for rule, (early, late) in zip(RULES, figures):
        cost = verdict["rules"]["/".join(rule)]["cost"]
        assert cost is None if early is None else cost == pytest.approx(early + LATE_WEIGHT * late)
    assert verdict["late_weight"] == LATE_WEIGHT


def test_the_late_weight_is_a_setting():
    # the ball screw's figures: record flags far early, posterior/p5 barely late; weighing late 500 times early
    # (a user for whom an interval late is unacceptable) turns the choice
    figures = dict(zip(RULES, [(5.249, 0.001), (5.249, 0.001), (0.0, 0.132), (0.0, 0.012)]))
    assert choose_end_of_life_rule(_tracked(figures))["verdict"] == "posterior"
    heavy = choose_end_of_life_rule(_tracked(figures), late_weight=500.0)
    assert (heavy["verdict"], heavy["faulty_at"], heavy["late_weight"]) == ("record", "p50", 500.0)
    assert compose_stage("run", []).companions.late_weight == LATE_WEIGHT  # the code default, overridable


def test_phm_track_auto_reads_the_rule_beside_the_pipeline():
    near = NearNominalFDI(4)
    defaults = {"verdict": "record", "faulty_at": "p50"}
    assert auto_rule(None) == defaults and auto_rule(near) == defaults  # the shipped file records none
    near.provenance = {"life_split": "lifetrain", "tracker_rule": {"verdict": "posterior", "faulty_at": "p5"}}
    assert auto_rule(near) == {"verdict": "posterior", "faulty_at": "p5"}
    # without a near-nominal FDI (the companions stage could not train one), the tracker check's rule
    check = TrackerCheck({"coverage_5_95": 0.9}, {"verdict": "posterior", "faulty_at": "p50"}, 40, 900)
    assert auto_rule(None, check=check) == {"verdict": "posterior", "faulty_at": "p50"}
    assert auto_rule(near, check=check) == {"verdict": "posterior", "faulty_at": "p5"}  # the FDI's choice first


def test_phm_track_auto_says_when_the_chosen_rule_flags_most_ends_of_life_early(caplog):
    """A robust actuator whose test command leaves a component unidentified: the companions' choice took a rule that
    flagged 80 % of the ends of life early (the steer270 probe); phm-track says so, and what the others did."""
    near = NearNominalFDI(4)
    rules = {"record/p5": {"eol_flagged_early": 0.8}, "record/p50": {"eol_flagged_early": 0.4}}
    near.provenance = {"life_split": "life", "tracker_rule": {"verdict": "record", "faulty_at": "p5", "rules": rules}}
    with caplog.at_level("WARNING", logger="phm_torch.apps.track"):
        assert auto_rule(near) == {"verdict": "record", "faulty_at": "p5"}
    assert "flagged 80 % of the ends of life on that split early" in caplog.text and "record/p50" in caplog.text
    caplog.clear()
    near.provenance["tracker_rule"] = {"verdict": "record", "faulty_at": "p50", "rules": rules}
    with caplog.at_level("WARNING", logger="phm_torch.apps.track"):
        auto_rule(near)
    assert "early" not in caplog.text
