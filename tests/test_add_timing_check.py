"""scripts/add_timing_check.py: an exported pipeline given the timing check's threshold phm-evaluate calibrates
(``timing_ratio_max``) from an independent store of its actuator and command; a pipeline without a consistency check
to scan with is refused."""

from __future__ import annotations

import json
from pathlib import Path

import h5py
import pytest
import surrogate_data
import torch
from script_module import script_module
from test_tracking import damage_config, make_pipeline

from phm_torch import provenance
from phm_torch.data.store import DATASET_FILE
from phm_torch.online.export import export_torchscript, read_metadata
from phm_torch.online.timing_check import TIMING_RATIO, calibrate_timing_ratio
from phm_torch.params import load_actuator
from phm_torch.pipelines.evaluate.calibration import noisy

pytestmark = pytest.mark.torchscript  # scripts, saves and loads TorchScript on purpose

PIPELINE = Path(__file__).resolve().parents[1] / "pretrained" / "online_surrogates_best.pt"


def _store(path: Path, nominal: torch.Tensor, prov: dict, monkeypatch) -> None:
    """A store whose val split holds 60 records of the nominal one, each scaled by a few per cent."""

    def signals(k: torch.Tensor, noise: float = 0.0, seed: int = 0) -> torch.Tensor:
        return nominal.to(torch.float64) * (1.0 + 0.04 * (k[:, :1] - 0.5))

    monkeypatch.setattr(surrogate_data, "signals", signals)
    surrogate_data.write_store(path, {"val": 60}, seed=3, n_time=nominal.numel())
    with h5py.File(path / DATASET_FILE, "r+") as f:
        f.attrs["metadata"] = json.dumps({"provenance": prov})


def test_the_threshold_is_phm_evaluates_on_the_store_and_goes_into_the_written_file(tmp_path, monkeypatch):
    torch.set_num_threads(1)
    module = torch.jit.load(str(PIPELINE))
    metadata = read_metadata(PIPELINE)
    _store(tmp_path / "store", module.nominal_record, metadata["provenance"], monkeypatch)
    out = tmp_path / "out" / "online.pt"
    report = script_module("add_timing_check").main(
        ["--pipeline", str(PIPELINE), "--data-dir", str(tmp_path / "store"), "--out", str(out)]
        + ["--formats", "torchscript", "--seed", "4", "--records", "60"]
    )
    # the same records, calibrated here with phm-evaluate's function
    with h5py.File(tmp_path / "store" / DATASET_FILE) as f:
        clean = torch.as_tensor(f["val/current"][()], dtype=torch.float64)
    signals = noisy(clean, float(module.interval_noise[0]), 4)
    with torch.no_grad():
        kept = signals[~module(signals.to(module.times.dtype))[3].bool()]
    assert report["records"] == kept.shape[0] >= 50
    assert report["timing_ratio_max"] == pytest.approx(calibrate_timing_ratio(module, kept, 20000.0))
    assert report["timing_ratio_max"] >= TIMING_RATIO
    written = read_metadata(out)
    assert written["timing_ratio_max"] == report["timing_ratio_max"]
    others = lambda m: {k: v for k, v in m.items() if k != "timing_ratio_max"}
    assert others(written) == others(metadata)  # everything else kept
    assert json.loads(out.with_suffix(".timing_check.json").read_text())["store"] == str(tmp_path / "store")


def test_a_pipeline_without_a_consistency_check_is_refused(tmp_path):
    reference = provenance.actuator_record("ema_reference", load_actuator())
    chirp = provenance.command_record("chirp", {"_target_": "phm_torch.command.Chirp"})
    export_torchscript(
        make_pipeline(),
        tmp_path / "online.pt",
        {"damage": damage_config(), "provenance": {"actuator": reference, "command": chirp}},
    )
    with pytest.raises(ValueError, match="no consistency check"):
        script_module("add_timing_check").main(
            ["--pipeline", str(tmp_path / "online.pt"), "--data-dir", str(tmp_path), "--out", str(tmp_path / "o.pt")]
        )
