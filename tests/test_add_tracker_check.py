"""scripts/add_tracker_check.py: a pipeline given the tracker check phm-run's companions stage writes (the tracker's
figures on histories with their truth, and the end-of-life rule chosen on them), which phm-track then reads."""

from __future__ import annotations

import json
import shutil
from types import SimpleNamespace

import pytest
from script_module import script_module
from test_tracking_app import fleet, fleet_truth  # noqa: F401  (fleet: the module fixture)

from phm_torch.apps.run_companions import RULES, companion_paths
from phm_torch.apps.track import auto_rule
from phm_torch.tracking.tracker_check import TrackerCheck

pytestmark = pytest.mark.torchscript  # loads TorchScript on purpose


def _copy(fleet, tmp_path):  # noqa: F811
    """The fixture's pipeline, records and index in a folder of this test's, with a truth.json beside the index."""
    life = tmp_path / "life"
    shutil.copytree(fleet / "records", life / "records")
    shutil.copy(fleet / "index.csv", life / "index.csv")
    (life / "truth.json").write_text(json.dumps(fleet_truth()))
    shutil.copy(fleet / "online.pt", tmp_path / "online.pt")
    return life, tmp_path / "online.pt"


def test_the_check_is_the_chosen_rules_track_and_phm_track_reads_its_rule(fleet, tmp_path):  # noqa: F811
    life, pipeline = _copy(fleet, tmp_path)
    script = script_module("add_tracker_check")
    report = script.main(["--pipeline", str(pipeline), "--life", str(life), "--work-dir", str(tmp_path / "work")])
    chosen = report["tracker_rule"]
    assert set(chosen["rules"]) == {"/".join(r) for r in RULES}
    rule = {"verdict": chosen["verdict"], "faulty_at": chosen["faulty_at"]}
    check = TrackerCheck.load(companion_paths(pipeline)["tracker_check"])
    assert check.rule == rule and check.histories == 3 and check.inspections == 12
    # the figures are the chosen rule's own track of these histories, as phm-track wrote them
    tracked = json.loads(
        (tmp_path / "work" / f"track_{rule['verdict']}_{rule['faulty_at']}" / "metrics.json").read_text()
    )
    assert check.figures == report["tracker_check_figures"]
    assert check.figures["coverage_5_95"] == tracked["tracker"]["coverage_5_95"]
    assert auto_rule(None, check=check) == rule  # phm-track verdict=auto / faulty_at=auto
    assert json.loads((tmp_path / "work" / "tracker_rules.json").read_text())["near_nominal"] is None


def test_missing_histories_and_a_pipeline_whose_near_nominal_fdi_chose_its_rule_are_refused(
    fleet,  # noqa: F811
    tmp_path,
    monkeypatch,
):
    life, pipeline = _copy(fleet, tmp_path)
    script = script_module("add_tracker_check")
    args = ["--pipeline", str(pipeline), "--work-dir", str(tmp_path / "work")]
    (life / "truth.json").unlink()
    with pytest.raises(ValueError, match=r"--life: .* holds no truth.json"):
        script.main([*args, "--life", str(life)])
    with pytest.raises(ValueError, match="--pipeline: .*nowhere.pt does not exist"):
        script.main(["--pipeline", str(tmp_path / "nowhere.pt"), "--life", str(life), "--work-dir", str(tmp_path)])
    (life / "truth.json").write_text(json.dumps(fleet_truth()))
    companion_paths(pipeline)["near_nominal"].write_text("x")
    chosen = SimpleNamespace(provenance={"tracker_rule": {"verdict": "posterior", "faulty_at": "p5"}})
    monkeypatch.setattr(script.NearNominalFDI, "load", classmethod(lambda cls, path: chosen))
    with pytest.raises(ValueError, match="records its own end-of-life rule"):
        script.main([*args, "--life", str(life)])
    assert not companion_paths(pipeline)["tracker_check"].exists()


def test_histories_of_another_actuator_are_refused_before_any_track(fleet, tmp_path):  # noqa: F811
    """phm-track only warns of a truth of another actuator; written beside the pipeline, a check measured on those
    histories would pass as its own."""
    from test_tracking import damage_config, make_pipeline

    from phm_torch import provenance
    from phm_torch.online.export import export_torchscript
    from phm_torch.params import load_actuator

    life, _ = _copy(fleet, tmp_path)
    pipeline = tmp_path / "made_for_reference.pt"
    reference = provenance.actuator_record("ema_reference", load_actuator())
    export_torchscript(make_pipeline(), pipeline, {"damage": damage_config(), "provenance": {"actuator": reference}})
    rudder = provenance.actuator_record("ema_hvdc_rudder", load_actuator("ema_hvdc_rudder"))
    (life / "truth.json").write_text(json.dumps({**fleet_truth(), "actuator": rudder}))
    script = script_module("add_tracker_check")
    with pytest.raises(ValueError, match="ema_hvdc_rudder"):
        script.main(["--pipeline", str(pipeline), "--life", str(life), "--work-dir", str(tmp_path / "work")])
    assert not companion_paths(pipeline)["tracker_check"].exists() and not (tmp_path / "work").exists()
