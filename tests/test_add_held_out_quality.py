"""scripts/add_held_out_quality.py: an exported pipeline given the held-out figures phm-evaluate records
(held_out_quality, identifiability) from an independent store of its actuator and command."""

from __future__ import annotations

import json

import h5py
import pytest
import surrogate_data
import torch
from script_module import script_module
from test_tracking import N_FULL, damage_config, make_pipeline

from phm_torch import provenance
from phm_torch.data.store import DATASET_FILE
from phm_torch.faults import FAULT_NAMES
from phm_torch.online.export import export_torchscript, read_metadata
from phm_torch.online.from_torchscript import pipeline_from_torchscript
from phm_torch.params import load_actuator
from phm_torch.pipelines.evaluate.calibration import noisy

pytestmark = pytest.mark.torchscript  # scripts, saves and loads TorchScript on purpose

CHIRP = provenance.command_record("chirp", {"_target_": "phm_torch.command.Chirp"})


def _records(pipe):
    """Synthetic records of the test pipeline's length: its mean plus its modes weighted by the fault vector."""

    def signals(k: torch.Tensor, noise: float = 0.0, seed: int = 0) -> torch.Tensor:
        weights = (k[:, :6] - 0.3) * 0.5
        return (pipe.mean_signal + weights @ pipe.modes.T).to(torch.float64)

    return signals


def _store(path, pipe, actuator: str, monkeypatch) -> None:
    monkeypatch.setattr(surrogate_data, "signals", _records(pipe))
    surrogate_data.write_store(path, {"val": 120}, seed=3, n_time=N_FULL)
    record = provenance.actuator_record(actuator, load_actuator(actuator))
    with h5py.File(path / DATASET_FILE, "r+") as f:
        f.attrs["metadata"] = json.dumps({"provenance": {"actuator": record, "command": CHIRP}})


@pytest.fixture(scope="module")
def exported(tmp_path_factory):
    root = tmp_path_factory.mktemp("held_out_quality")
    pipe = make_pipeline()
    reference = provenance.actuator_record("ema_reference", load_actuator())
    meta = {"damage": damage_config(), "provenance": {"actuator": reference, "command": CHIRP}}
    export_torchscript(pipe, root / "online.pt", meta)
    return root, pipe


def test_the_figures_are_phm_evaluates_on_the_store_and_go_into_the_written_file(exported, tmp_path, monkeypatch):
    root, pipe = exported
    _store(tmp_path / "store", pipe, "ema_reference", monkeypatch)
    script = script_module("add_held_out_quality")
    out = tmp_path / "out" / "online.pt"
    report = script.main(
        ["--pipeline", str(root / "online.pt"), "--data-dir", str(tmp_path / "store"), "--out", str(out)]
        + ["--formats", "torchscript", "--seed", "4"]
    )
    # the same records through the pipeline as the file holds it, counted here
    rebuilt, _ = pipeline_from_torchscript(root / "online.pt")
    with h5py.File(tmp_path / "store" / DATASET_FILE) as f:
        clean = torch.as_tensor(f["val/current"][()], dtype=torch.float64)
        healthy = torch.as_tensor(f["val/healthy"][()]).bool()
    noise = float(rebuilt.interval_noise[0])
    assert report["noise"] == noise and report["beyond_drive_range"] == 0
    with torch.no_grad():
        _, score, _, ood, _ = rebuilt(noisy(clean, noise, 4))
    answered = ~ood.bool()
    said_healthy, truth = (score > 0)[answered], healthy[answered]
    quality = report["held_out_quality"]
    assert quality["records"] == 120 and quality["faulty_records"] == int((~truth).sum())
    assert quality["missed_faulty"] == pytest.approx(float((said_healthy & ~truth).sum()) / int((~truth).sum()))
    assert quality["false_alarm"] == pytest.approx(float((~said_healthy & truth).sum()) / int(truth.sum()))
    assert quality["rul_err_median_full_flow"] is None  # not measured by the script
    assert set(report["identifiability"]) == set(FAULT_NAMES)
    written = read_metadata(out)
    assert written["held_out_quality"] == quality and written["identifiability"] == report["identifiability"]
    assert written["provenance"] == read_metadata(root / "online.pt")["provenance"]  # everything else kept
    assert json.loads(out.with_suffix(".held_out_quality.json").read_text())["store"] == str(tmp_path / "store")


def test_a_store_of_another_actuator_or_without_the_split_is_refused(exported, tmp_path, monkeypatch):
    root, pipe = exported
    _store(tmp_path / "rudder", pipe, "ema_hvdc_rudder", monkeypatch)
    script = script_module("add_held_out_quality")
    args = ["--pipeline", str(root / "online.pt"), "--out", str(tmp_path / "o.pt"), "--formats", "torchscript"]
    with pytest.raises(ValueError, match="ema_hvdc_rudder"):
        script.main([*args, "--data-dir", str(tmp_path / "rudder")])
    _store(tmp_path / "reference", pipe, "ema_reference", monkeypatch)
    with pytest.raises(ValueError, match="split: 'test' not in store"):
        script.main([*args, "--data-dir", str(tmp_path / "reference"), "--split", "test"])
    assert not (tmp_path / "o.pt").exists()


def test_a_pipeline_without_calibrated_noise_needs_noise_given(tmp_path, monkeypatch):
    """Its interval noise levels are placeholders (zeros): reading the records noise-free would flatter it."""
    pipe = make_pipeline(calibrated=False)
    reference = provenance.actuator_record("ema_reference", load_actuator())
    meta = {"damage": damage_config(), "provenance": {"actuator": reference, "command": CHIRP}}
    export_torchscript(pipe, tmp_path / "raw.pt", meta)
    _store(tmp_path / "store", pipe, "ema_reference", monkeypatch)
    script = script_module("add_held_out_quality")
    args = ["--pipeline", str(tmp_path / "raw.pt"), "--data-dir", str(tmp_path / "store"), "--formats", "torchscript"]
    with pytest.raises(ValueError, match="no calibrated noise level.*--noise"):
        script.main([*args, "--out", str(tmp_path / "a.pt")])
    with pytest.raises(ValueError, match="--noise must be .* got -0.1"):
        script.main([*args, "--out", str(tmp_path / "a.pt"), "--noise", "-0.1"])
    assert not (tmp_path / "a.pt").exists()
    report = script.main([*args, "--out", str(tmp_path / "b.pt"), "--noise", "0.02"])
    assert report["noise"] == 0.02 and read_metadata(tmp_path / "b.pt")["held_out_quality"]["records"] == 120
