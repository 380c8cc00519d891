"""phm-track end to end on a small synthetic pipeline and records: track.json, OOD, maintenance, resume of an
interrupted run, and one-line errors for bad input."""

from __future__ import annotations

import json

import pytest
import torch
from test_tracking import N_FULL, damage_config, make_pipeline

from phm_torch.io import write_measurement
from phm_torch.online.export import export_torchscript

pytestmark = pytest.mark.torchscript  # scripts, saves or loads TorchScript on purpose


def record(pipe, alpha: torch.Tensor) -> dict:
    zeros = torch.zeros(N_FULL, dtype=torch.float64)
    return {
        "time": torch.arange(N_FULL, dtype=torch.float64) / 20000.0,
        "command": zeros,
        "position": zeros,
        "current": pipe.mean_signal + pipe.modes @ alpha,
    }


@pytest.fixture(scope="module")
def fleet(tmp_path_factory):
    """A pipeline (with its damage config in the metadata) and an index of 3 actuators x 4 inspections."""
    root = tmp_path_factory.mktemp("fleet")
    pipe = make_pipeline()
    export_torchscript(pipe, root / "online.pt", {"damage": damage_config()})
    export_torchscript(make_pipeline(calibrated=False), root / "raw.pt", {"damage": damage_config()})
    export_torchscript(pipe, root / "old.pt")  # no damage config: the composed fallback
    g = torch.Generator().manual_seed(0)
    rows = ["actuator,hours,file,event"]
    for a in range(3):
        base = torch.randn(6, generator=g, dtype=torch.float64) * 0.3
        for i in range(4):
            path = root / "records" / f"A{a}_{i}.csv"
            data = record(pipe, base + 0.02 * i)
            if a == 1 and i == 2:  # not like any training record
                data["current"] = torch.randn(N_FULL, generator=g, dtype=torch.float64)
            write_measurement(path, data)
            rows.append(f"A{a},{200 * i},records/{path.name},{'maintenance' if a == 2 and i == 2 else ''}")
    (root / "index.csv").write_text("\n".join(rows) + "\n")
    return root


def run(compose, root, out, *extra):
    from phm_torch.apps.track import track

    return track(
        compose(
            "track",
            [
                f"index={root / 'index.csv'}",
                f"pipeline={root / 'online.pt'}",
                f"out_dir={out}",
                "n_particles=64",
                "rul_particles=16",
                "chunk_size=1",
                *extra,
            ],
        )
    )


def test_track_json_fleet_ood_and_maintenance(fleet, compose, tmp_path):
    metrics, _ = run(compose, fleet, tmp_path)
    track = json.loads((tmp_path / "track.json").read_text())
    assert metrics["inspections"] == 12 and metrics["damage_source"].endswith("metadata")
    insp = track["actuators"]["A1"]["inspections"]
    assert insp[2]["out_of_distribution"] and not insp[2]["fused"] and insp[2]["ood_reasons"]
    assert all(i["fused"] for k, i in enumerate(insp) if k != 2)
    keys = {
        "hours",
        "file",
        "k_hat",
        "k_filtered",
        "k_interval",
        "rate_scale",
        "p_faulty",
        "healthy",
        "rul_hours",
        "rul_censored",
        "out_of_distribution",
        "ood_reasons",
        "fused",
        "snapshot_rul_hours",
        "snapshot_rul_censored",
        "messages",
    }
    assert keys <= set(insp[0])
    assert insp[0]["messages"] == [] and all(m.split(":")[0] in insp[2]["ood_reasons"] for m in insp[2]["messages"])
    assert insp[2]["messages"]  # a refused record says why, one line a reason (phm-predict's)
    for i in (x for a in track["actuators"].values() for x in a["inspections"]):
        if i["rul_hours"] is not None:  # censored bounds are null, never the horizon
            assert all(v is None or v < 20000.0 for v in i["rul_hours"].values())
            assert i["rul_censored"] == any(v is None for v in i["rul_hours"].values())
    a2 = track["actuators"]["A2"]["inspections"]
    assert a2[2]["event"] == "maintenance"
    width = [i["rate_scale"]["p95"] / i["rate_scale"]["p5"] for i in a2]
    assert width[2] > width[1]  # the restarted track forgets the old wear rate
    assert len(track["fleet"]) == 3
    fleet_file = json.loads((tmp_path / "fleet.json").read_text())
    assert fleet_file["fleet"] == track["fleet"]
    assert fleet_file["actuator"] == track["actuator"]
    assert fleet_file["command"] == track["command"] and fleet_file["pipeline"] == track["pipeline"]


def fleet_truth(with_k: bool = True) -> dict:
    """A truth.json for the fleet fixture's 3 x 4 inspections: A0 ends its life at 700 h, the others never; k_true a
    small ramp from nominal (without ``with_k``: the end of life and the hours only, as another tool may write it)."""
    from test_tracking import NOMINAL

    actuators = {}
    for a in range(3):
        eol = 700.0 if a == 0 else None
        rows = []
        for i in range(4):
            k = [v + (0.01 * (i + 1) if j < 6 else 0.0) for j, v in enumerate(NOMINAL)]
            row = {"hours": 200.0 * i, "healthy": True, "rul_true": None if eol is None else eol - 200.0 * i}
            rows.append({**row, "k_true": k} if with_k else row)
        actuators[f"A{a}"] = {"eol_hours": eol, "inspections": rows, **({"rate_scale": 1.0} if with_k else {})}
    return {"every_hours": 200.0, "actuators": actuators} if with_k else {"actuators": actuators}


def test_with_truth_the_tracking_limit_is_scored_beside_the_run(fleet, compose, tmp_path, caplog):
    (tmp_path / "truth.json").write_text(json.dumps(fleet_truth()))
    metrics, _ = run(compose, fleet, tmp_path / "a", f"truth={tmp_path / 'truth.json'}")
    saved = json.loads((tmp_path / "a" / "metrics.json").read_text())
    assert saved["limit"] == metrics["limit"]
    limit = metrics["limit"]
    assert limit["error_std"] == 1e-4 and limit["components_as_read"] == [] and limit["n_actuators"] == 3
    assert set(limit["tracking"]) == set(saved["tracker"])  # scored as the run itself
    assert set(limit["classifier_on_true_k"]) >= {"eol_flagged_within_one_inspection", "eol_never_flagged"}
    off, _ = run(compose, fleet, tmp_path / "b", f"truth={tmp_path / 'truth.json'}", "limit_error_std=null")
    assert off["limit"] is None
    (tmp_path / "bare.json").write_text(json.dumps(fleet_truth(with_k=False)))
    with caplog.at_level("INFO", logger="phm_torch"):
        bare, _ = run(compose, fleet, tmp_path / "c", f"truth={tmp_path / 'bare.json'}")
    assert bare["limit"] is None and "no k_true at every inspection" in caplog.text
    # a truth of another actuator than the pipeline's: scored, but no limit (its classifier says nothing of that k)
    (tmp_path / "other.json").write_text(
        json.dumps({**fleet_truth(), "actuator": {"name": "flap", "sha256": "f" * 64}})
    )
    with caplog.at_level("WARNING", logger="phm_torch"):
        other, _ = run(compose, fleet, tmp_path / "d", f"truth={tmp_path / 'other.json'}", "actuator=ema_reference")
    assert other["limit"] is None and other["tracker"] is not None
    assert "truth is of the actuator flap (sha256 ffffffff), the pipeline of ema_reference" in caplog.text
    # scored all the same, the one-inspection window from the inspections' spacing; the figures drawn
    scored = json.loads((tmp_path / "c" / "metrics.json").read_text())
    assert scored["settings"]["every_hours"] == 200.0 and "median spacing, 200 h" in caplog.text
    assert scored["tracker"]["coverage_5_95_n"] == 4 and (tmp_path / "c" / "life_damage.png").is_file()


def test_only_a_refused_inspection_is_logged_as_not_fused(fleet, compose, tmp_path, caplog, monkeypatch):
    """A record's messages say what was corrected (fused) as well as what was refused: the log says "not fused"
    only for the latter (it had said so for every message, a corrected probe offset included)."""
    import phm_torch.apps.track as app

    real = app.inspect_record

    def with_a_correction(*args, **kwargs):
        found = real(*args, **kwargs)
        return {**found, "messages": [*found["messages"], "probe_offset: removed"]}

    monkeypatch.setattr(app, "inspect_record", with_a_correction)
    caplog.set_level("WARNING")
    run(compose, fleet, tmp_path)
    lines = [r.getMessage() for r in caplog.records if "probe_offset: removed" in r.getMessage()]
    refused = [line for line in lines if "A1_2.csv" in line]
    assert len(lines) == 12 and refused and all("not fused" in line for line in refused)
    assert not any("not fused" in line for line in lines if "A1_2.csv" not in line)


def test_an_interrupted_run_resumes_to_the_same_result(fleet, compose, tmp_path, monkeypatch):
    import phm_torch.apps.track as app

    run(compose, fleet, tmp_path / "whole")
    calls = {"n": 0}
    real = app.inspect_record

    def flaky(*args, **kwargs):
        calls["n"] += 1
        if calls["n"] == 9:  # dies inside the second actuator (after the fleet check's 3 and the first's 4)
            raise KeyboardInterrupt
        return real(*args, **kwargs)

    monkeypatch.setattr(app, "inspect_record", flaky)
    with pytest.raises(KeyboardInterrupt):
        run(compose, fleet, tmp_path / "resumed")
    assert (tmp_path / "resumed" / "state" / "A0.pt").is_file()
    assert not (tmp_path / "resumed" / "state" / "A1.pt").exists()
    monkeypatch.setattr(app, "inspect_record", real)
    resumed = json.loads(json.dumps(run(compose, fleet, tmp_path / "resumed")[1]["track"]))
    expected = json.loads((tmp_path / "whole" / "track.json").read_text())
    assert resumed["actuators"] == expected["actuators"] and resumed["fleet"] == expected["fleet"]


@pytest.mark.parametrize(
    "rows, message",
    [
        (
            ["A0,0,records/A0_0.csv,", "A0,400,records/A0_1.csv,", "A0,200,records/A0_2.csv,"],
            r"line 4 \(actuator A0\): hours 200 not after the previous inspection's 400 \(line 3\)",
        ),
        (["A0,0,records/A0_0.csv,", "A0,0,records/A0_1.csv,"], r"line 3 \(actuator A0\): duplicate hours 0 \(line 2\)"),
        (["A0,0,records/nope.csv,"], r"line 2 \(actuator A0\): no such file 'records/nope.csv'"),
        (["A0,0,records/A0_0.csv,repair"], r"line 2 \(actuator A0\): unknown event 'repair'"),
        (["A0,ten,records/A0_0.csv,"], r"line 2 \(actuator A0\): hours 'ten' is not a number"),
    ],
)
def test_bad_index_rows_are_one_line_errors(fleet, compose, tmp_path, rows, message):
    index = tmp_path / "index.csv"
    index.write_text(
        "\n".join(["actuator,hours,file,event", *[r.replace("records/", f"{fleet}/records/") for r in rows]]) + "\n"
    )
    with pytest.raises(ValueError, match=message.replace("records/", ".*records/")) as err:
        run(compose, fleet, tmp_path / "out", f"index={index}")
    assert "\n" not in str(err.value)


def test_missing_columns_uncalibrated_pipeline_and_old_pipeline(fleet, compose, tmp_path, caplog):
    index = tmp_path / "nofile.csv"
    index.write_text("actuator,hours\nA0,0\n")
    with pytest.raises(ValueError, match=r"missing column\(s\) \['file'\]"):
        run(compose, fleet, tmp_path, f"index={index}")
    with pytest.raises(ValueError, match="no calibrated k_hat intervals"):
        run(compose, fleet, tmp_path, f"pipeline={fleet / 'raw.pt'}")
    # an older pipeline: the composed conf/damage, whose F is not this pipeline's, is refused by name
    with pytest.raises(ValueError, match="does not match the pipeline's propagators"):
        run(compose, fleet, tmp_path, f"pipeline={fleet / 'old.pt'}")
    assert any("carries no damage config" in r.getMessage() for r in caplog.records)


def test_a_response_beside_the_pipeline_is_inverted_and_one_for_another_pipeline_refused(fleet, compose, tmp_path):
    import shutil

    import numpy as np

    from phm_torch.online.loaded import load_pipeline
    from phm_torch.tracking.response import fit_response, probe_k_hat

    shutil.copy(fleet / "online.pt", tmp_path / "online.pt")
    probe = probe_k_hat(load_pipeline(tmp_path / "online.pt").module)
    rng = np.random.default_rng(0)
    k = rng.uniform(0.0, 1.0, (2000, 8))
    fit_response(k, 0.5 + 0.6 * k, pipeline={"probe_k_hat": probe, "source": "online.pt"}).save(
        tmp_path / "online.fdi_response.json"
    )
    _metrics, objects = run(compose, fleet, tmp_path / "out", f"pipeline={tmp_path / 'online.pt'}")
    insp = objects["track"]["actuators"]["A0"]["inspections"][0]
    assert "backlash" in objects["track"]["tracker"]["fdi_response"]["corrected"]
    hat, corrected = insp["k_hat"]["backlash"], insp["k_hat_corrected"]["backlash"]
    assert corrected == pytest.approx(min(max((hat - 0.5) / 0.6, 0.0), 1.0), abs=0.02)  # h(k) = 0.5 + 0.6 k inverted
    low, high = insp["k_hat_corrected_interval"]["backlash"]  # the interval the filter read, through the inverse too
    assert low <= corrected <= high and (high - low) >= (insp["k_interval"]["backlash"][1] - hat) * 0.9
    without = run(compose, fleet, tmp_path / "none", f"pipeline={tmp_path / 'online.pt'}", "response=null")[1]
    assert "k_hat_corrected" not in without["track"]["actuators"]["A0"]["inspections"][0]
    fit_response(k, k, pipeline={"probe_k_hat": [v + 0.01 for v in probe], "source": "other.pt"}).save(
        tmp_path / "other.json"
    )
    with pytest.raises(ValueError, match=r"fitted for another pipeline \(other.pt\)"):
        run(compose, fleet, tmp_path / "x", f"response={tmp_path / 'other.json'}")
    with pytest.raises(ValueError, match="response: no such file"):
        run(compose, fleet, tmp_path / "x", f"response={tmp_path / 'nope.json'}")
    with pytest.raises(ValueError, match="response_out=.*needs truth="):
        run(compose, fleet, tmp_path / "x", f"response_out={tmp_path / 'r.json'}")


def test_a_fleet_that_reads_one_damage_vector_at_its_first_inspections_is_refused(compose, tmp_path, monkeypatch):
    """Every actuator's first record alike (one bench's difference, not wear): the fleet check refuses to fuse
    anything and says why; with action=warn it tracks them as read."""
    pipe = make_pipeline()
    export_torchscript(pipe, tmp_path / "online.pt", {"damage": damage_config()})
    alpha = torch.full((6,), 0.4, dtype=torch.float64)
    rows = ["actuator,hours,file"]
    for a in range(3):
        for i in range(3):
            path = tmp_path / "records" / f"A{a}_{i}.csv"
            write_measurement(path, record(pipe, alpha + 0.01 * i))
            rows.append(f"A{a},{200 * i},records/{path.name}")
    (tmp_path / "index.csv").write_text("\n".join(rows) + "\n")
    with torch.no_grad():
        k_first = pipe(record(pipe, alpha)["current"].unsqueeze(0))[0][0]
    assert float(k_first[:6].abs().max()) > 0.1  # the synthetic FDI reads these records as damaged
    refused, objects = run(compose, tmp_path, tmp_path / "out", "fleet_check.min_actuators=2")
    assert refused["fleet_check"]["offset"] and refused["fused"] == 0
    insp = objects["track"]["actuators"]["A1"]["inspections"]
    assert all(i["out_of_distribution"] and "fleet_offset" in i["ood_reasons"] for i in insp)
    assert all(i["rul_hours"] is None for i in insp)
    import phm_torch.apps.track as track_app

    reads = []
    read = track_app._read
    monkeypatch.setattr(track_app, "_read", lambda path, *a: reads.append(path) or read(path, *a))
    warned, _ = run(compose, tmp_path, tmp_path / "warn", "fleet_check.min_actuators=2", "fleet_check.action=warn")
    assert warned["fleet_check"]["offset"] and warned["fused"] == 9
    assert sorted(reads) == sorted(set(reads)) and len(reads) == 9  # each record read once, the first ones too
    unchecked, _ = run(compose, tmp_path, tmp_path / "default", "resume=false")
    assert not unchecked["fleet_check"]["checked"] and unchecked["fused"] == 9  # 3 actuators < min_actuators 5


def test_a_fleet_offset_that_a_current_probe_explains_is_named_and_a_baseline_calibrates_it(compose, tmp_path):
    """Every record of a fleet through a probe of gain 1.02 and offset 0.01 A: the fleet check's message names the
    probe the fleet's mean first record shows (said, not applied); with a healthy record of that bench as baseline
    the probe is calibrated and every inspection reads as the same fleet's records through a perfect probe."""
    pipe = make_pipeline()
    pipe.nominal_record.copy_(pipe.mean_signal)  # a nominal record to compare with (the synthetic FDI's reading
    export_torchscript(pipe, tmp_path / "online.pt", {"damage": damage_config()})  # of it is not nominal: flagged)
    for fleet_name, probe in (("clean", lambda x: x), ("probe", lambda x: 1.02 * x + 0.01)):
        rows = ["actuator,hours,file"]
        for a in range(6):
            alpha = 0.01 * torch.randn(6, generator=torch.Generator().manual_seed(a), dtype=torch.float64)
            for i in range(2):
                data = record(pipe, alpha + 0.01 * i)
                data["current"] = probe(data["current"])
                path = tmp_path / fleet_name / f"A{a}_{i}.csv"
                write_measurement(path, data)
                rows.append(f"A{a},{200 * i},{path.name}")
        (tmp_path / fleet_name / "index.csv").write_text("\n".join(rows) + "\n")
    healthy = record(pipe, torch.zeros(6, dtype=torch.float64))
    healthy["current"] = 1.02 * healthy["current"] + 0.01
    write_measurement(tmp_path / "healthy.csv", healthy)

    def track(name, *extra):
        from phm_torch.apps.track import track as run_track

        overrides = [f"index={tmp_path / name / 'index.csv'}", f"pipeline={tmp_path / 'online.pt'}"]
        overrides += [f"out_dir={tmp_path / 'out' / str(len(extra))}{name}", "n_particles=64", "rul_particles=16"]
        return run_track(compose("track", [*overrides, *extra]))

    refused, _ = track("probe")
    assert refused["fleet_check"]["offset"] and refused["fused"] == 0
    suspected = refused["fleet_check"]["probe_suspected"]
    assert suspected["gain"] == pytest.approx(1.02, abs=2e-3) and suspected["offset"] == pytest.approx(0.01, abs=2e-3)
    assert (
        "a probe error, which a healthy record of this bench as baseline= calibrates"
        in refused["fleet_check"]["message"]
    )
    # a pipeline whose intervals are too wide to see the k_hat offset: the mean record still shows the probe
    wide, _ = track("probe", "fleet_check.z_threshold=1000")
    assert wide["fleet_check"]["offset"] and not wide["fleet_check"]["components"] and wide["fused"] == 0
    assert wide["fleet_check"]["probe_suspected"]["gain"] == pytest.approx(1.02, abs=2e-3)
    assert "the k_hat offset it leaves is within the intervals" in wide["fleet_check"]["message"]
    clean, clean_objects = track("clean", "fleet_check.action=warn")
    assert "probe_suspected" not in clean["fleet_check"] and clean["probe_calibration"] is None
    quiet, _ = track("clean", "fleet_check.z_threshold=1000")
    assert not quiet["fleet_check"]["offset"] and quiet["fused"] == 12
    base = f"baseline={tmp_path / 'healthy.csv'}"
    calibrated, objects = track("probe", base, "fleet_check.action=warn")
    assert calibrated["probe_calibration"]["gain"] == pytest.approx(1.02, abs=1e-9)
    for a in ("A0", "A5"):
        pairs = zip(
            objects["track"]["actuators"][a]["inspections"], clean_objects["track"]["actuators"][a]["inspections"]
        )
        for got, want in pairs:
            assert got["k_hat"] == pytest.approx(want["k_hat"], abs=1e-6)


def test_a_near_nominal_fdi_beside_the_pipeline_is_read_near_nominal(fleet, compose, tmp_path, caplog):
    import shutil

    from phm_torch.online.loaded import load_pipeline
    from phm_torch.tracking.near_nominal import NearNominalFDI
    from phm_torch.tracking.response import probe_k_hat

    shutil.copy(fleet / "online.pt", tmp_path / "online.pt")
    module = load_pipeline(tmp_path / "online.pt").module
    near = NearNominalFDI(int(module.gappy.modes_hat.shape[1]), n_hidden=8, gate=1.0, noise_levels=(0.5,))
    near.half_widths_.fill_(0.01)
    near.provenance = {"probe_k_hat": probe_k_hat(module), "source": "online.pt"}
    near.save(tmp_path / "online.near_nominal.pt")
    _, objects = run(compose, fleet, tmp_path / "out", f"pipeline={tmp_path / 'online.pt'}")
    track = objects["track"]
    insp = [i for a in track["actuators"].values() for i in a["inspections"] if not i["out_of_distribution"]]
    assert insp and all("k_hat_near_nominal" in i for i in insp)
    first = insp[0]
    assert first["k_hat_near_nominal"]["eccentricity_phase"] == first["k_hat"]["eccentricity_phase"]
    low, high = first["k_hat_near_nominal_interval"]["backlash"]
    assert high - low == pytest.approx(0.02, abs=1e-6) and low <= first["k_hat_near_nominal"]["backlash"] <= high
    assert track["tracker"]["near_nominal"]["source"] == "online.pt"
    # another near-nominal file beside the pipeline: a resumed run recomputes, it does not reuse the old states
    near.half_widths_.fill_(0.02)
    near.save(tmp_path / "online.near_nominal.pt")
    _, again = run(compose, fleet, tmp_path / "out", f"pipeline={tmp_path / 'online.pt'}")
    first_again = next(
        i for a in again["track"]["actuators"].values() for i in a["inspections"] if not i["out_of_distribution"]
    )
    low, high = first_again["k_hat_near_nominal_interval"]["backlash"]
    assert high - low == pytest.approx(0.04, abs=1e-6)
    warned = [r.getMessage() for r in caplog.records if "=auto: no online." in r.getMessage()]
    assert warned and all("response=auto" in m and "response_out=" in m for m in warned)  # no response beside it
    caplog.clear()
    _, none = run(compose, fleet, tmp_path / "none", f"pipeline={tmp_path / 'online.pt'}", "near_nominal=null")
    assert not any("k_hat_near_nominal" in i for a in none["track"]["actuators"].values() for i in a["inspections"])
    assert not any("near_nominal=auto" in r.getMessage() for r in caplog.records)  # null: none asked for


def test_a_whole_record_near_nominal_fdi_is_read_on_every_sample(fleet, compose, tmp_path):
    """The near-nominal FDI that projects the whole record on its own basis (``n_full``) is read by phm-track as the
    gappy one is; its reading is that of its own projection of the record."""
    import shutil

    import numpy as np

    from phm_torch.faults import FAULT_NAMES
    from phm_torch.io import read_measurement
    from phm_torch.online.loaded import load_pipeline
    from phm_torch.tracking.near_nominal import NearNominalFDI
    from phm_torch.tracking.response import probe_k_hat

    shutil.copy(fleet / "online.pt", tmp_path / "online.pt")
    module = load_pipeline(tmp_path / "online.pt").module
    near = NearNominalFDI(4, n_hidden=8, gate=1.0, noise_levels=(0.5,), n_full=int(module.n_full))
    currents = [read_measurement(f).current for f in sorted((fleet / "records").glob("*.csv"))]
    near.fit_basis(torch.tensor(np.stack(currents)))  # the fleet's own records: 12 > 4 directions
    near.half_widths_.fill_(0.01)
    near.provenance = {"probe_k_hat": probe_k_hat(module), "source": "online.pt"}
    near.save(tmp_path / "online.near_nominal.pt")
    _, objects = run(compose, fleet, tmp_path / "out", f"pipeline={tmp_path / 'online.pt'}")
    actuator, info = next(iter(objects["track"]["actuators"].items()))
    first = next(i for i in info["inspections"] if not i["out_of_distribution"])
    current = torch.tensor(read_measurement(fleet / first["file"]).current).reshape(1, -1)
    alpha, readable = near.coefficients(module, current)
    with torch.no_grad():
        expected = near(alpha, torch.tensor([first["noise"]], dtype=torch.float64))[0]
    got = torch.tensor([first["k_hat_near_nominal"][n] for n in FAULT_NAMES], dtype=torch.float64)
    assert bool(readable[0]) and torch.allclose(got[:6], expected[:6], atol=1e-6), actuator


def test_a_tracker_check_beside_the_pipeline_is_warned_of_and_one_for_another_pipeline_refused(
    fleet, compose, tmp_path, caplog
):
    """The companions stage's figures of the tracker on simulated histories of this actuator: phm-track reads them
    beside the pipeline, warns where they fall short (a ball screw's 41 % coverage), records them in its metrics,
    and refuses a file measured with another pipeline."""
    import shutil

    from phm_torch.online.loaded import load_pipeline
    from phm_torch.tracking.response import probe_k_hat
    from phm_torch.tracking.tracker_check import TrackerCheck

    shutil.copy(fleet / "online.pt", tmp_path / "online.pt")
    probe = probe_k_hat(load_pipeline(tmp_path / "online.pt").module)
    figures = {"coverage_5_95": 0.41, "eol_flagged_early": 1.0, "alpha_lambda": 0.33}
    rule = {"verdict": "record", "faulty_at": "p50"}
    TrackerCheck(figures, rule, 40, 843, {"probe_k_hat": probe, "source": "online.pt"}).save(
        tmp_path / "online.tracker_check.json"
    )
    with caplog.at_level("WARNING", logger="phm_torch.apps.track"):
        metrics, _ = run(compose, fleet, tmp_path / "out", f"pipeline={tmp_path / 'online.pt'}")
    assert "on 40 simulated run-to-failure histories of this actuator (843 inspections" in caplog.text
    assert "held the true RUL on 41 %" in caplog.text and "flagged 100 % of the ends of life early" in caplog.text
    assert metrics["tracker_check"]["figures"]["coverage_5_95"] == 0.41
    caplog.clear()
    with caplog.at_level("WARNING", logger="phm_torch.apps.track"):  # another rule than the one measured: said
        run(compose, fleet, tmp_path / "p5", f"pipeline={tmp_path / 'online.pt'}", "faulty_at=p5")
    assert "was not the one measured" in caplog.text
    caplog.clear()
    with caplog.at_level("WARNING", logger="phm_torch.apps.track"):
        none = run(compose, fleet, tmp_path / "none", f"pipeline={tmp_path / 'online.pt'}", "tracker_check=null")[0]
    assert none["tracker_check"] is None and "simulated run-to-failure" not in caplog.text
    TrackerCheck(figures, rule, 40, 843, {"probe_k_hat": [v + 0.01 for v in probe], "source": "other.pt"}).save(
        tmp_path / "other.json"
    )
    with pytest.raises(ValueError, match=r"tracker check was measured for another pipeline \(other.pt\)"):
        run(compose, fleet, tmp_path / "x", f"tracker_check={tmp_path / 'other.json'}")
