"""The drive range: training records whose current exceeds ``drive_range`` x the actuator's current limit (a protected
drive trips there) calibrate no out-of-distribution threshold and can be left out of every fit, and the input contract
calls such a record ``overcurrent``."""

from __future__ import annotations

import json

import h5py
import pytest
import torch
from surrogate_data import write_store

from phm_torch.apps.train import settings_from_config, train_surrogates
from phm_torch.drive_range import drive_bound, within_drive_range
from phm_torch.online.input_contract import InputContract
from phm_torch.pipelines.train.data import load_data
from phm_torch.provenance import digest
from phm_torch.surrogates.data import SplitData


def test_split_rows_and_peak_current():
    current = torch.tensor([[0.0, -3.0, 1.0], [2.0, float("nan"), -1.0], [0.5, 0.5, 0.5]])
    split = SplitData("train", torch.zeros(3, 8), current, torch.tensor([True, False, True]))
    assert split.peak_current().tolist() == [3.0, 2.0, 0.5]
    kept = split.rows(split.peak_current() <= 2.0)
    assert len(kept) == 2 and kept.healthy.tolist() == [False, True] and kept.name == "train"


def test_one_rule_for_within_the_drive_range_missing_samples_ignored():
    current = torch.tensor([[0.0, -3.0, 1.0], [2.0, float("nan"), -1.0], [0.5, 0.5, 0.5]])
    assert within_drive_range(current, 2.0).tolist() == [False, True, True]
    assert within_drive_range(current, None).tolist() == [True, True, True]
    assert within_drive_range(current[1], 1.5).tolist() is False  # one record (n,): a 0-d answer


def test_drive_bound():
    actuator = {"name": "a", "values": {"current_limit": 20.0}}
    assert drive_bound(actuator, 2.0) == 40.0
    assert drive_bound(actuator, None) is None and drive_bound(None, 2.0) is None
    assert drive_bound({"name": "a", "values": {}}, 2.0) is None


def _with_limit(store, limit: float) -> None:
    """Record an actuator with this current limit in a synthetic store's metadata."""
    with h5py.File(store / "dataset.h5", "r+") as f:
        meta = json.loads(f.attrs["metadata"])
        values = {"current_limit": limit}
        meta["provenance"] = {"actuator": {"name": "synthetic", "sha256": digest(values), "values": values}}
        f.attrs["metadata"] = json.dumps(meta)


def test_load_data_marks_the_records_beyond_the_drive_range_and_can_leave_them_out(compose, tmp_path):
    store = write_store(tmp_path / "store", {"train": 200, "val": 50})
    with h5py.File(store / "dataset.h5", "r") as f:
        peaks = torch.as_tensor(f["train"]["current"][:]).abs().amax(1)
    limit = float(peaks.quantile(0.9)) / 2.0  # a tenth of the records beyond twice the limit
    _with_limit(store, limit)
    base = [f"data_dir={store}", f"out_dir={tmp_path / 'out'}"]
    settings = settings_from_config(compose("train", base))
    assert settings.drive_range == 2.0 and not settings.fit_within_drive_range  # the shipped defaults
    data = load_data(settings, {})
    beyond = peaks > 2.0 * limit
    assert data.current_bound == pytest.approx(2.0 * limit) and data.beyond_range == int(beyond.sum()) > 0
    assert len(data.train) == 200 and torch.equal(data.inside, ~beyond)  # kept in the fits, marked
    left_out = load_data(settings_from_config(compose("train", [*base, "fit_within_drive_range=true"])), {})
    assert len(left_out.train) == 200 - int(beyond.sum()) and left_out.beyond_range == 0
    assert float(left_out.train.peak_current().max()) <= 2.0 * limit and len(left_out.val) == 50  # val whole
    none = load_data(settings_from_config(compose("train", [*base, "drive_range=null"])), {})
    assert none.current_bound is None and none.inside is None and len(none.train) == 200
    with pytest.raises(ValueError, match="drive_range"):
        settings_from_config(compose("train", [*base, "drive_range=0.5"]))


def test_contract_calls_a_current_beyond_the_drive_range_overcurrent():
    current = torch.linspace(0.0, 5.0, 101, dtype=torch.float64)
    model = object()
    assert "overcurrent" in InputContract(current_bound=4.0).current_reasons(model, current, 0.01)
    assert "overcurrent" not in InputContract(current_bound=6.0).current_reasons(model, current, 0.01)
    assert "overcurrent" not in InputContract().current_reasons(model, current, 0.01)  # an older pipeline: unchecked
    assert InputContract.of(model, {"drive_current_bound": 40.0}, None).current_bound == 40.0
    assert InputContract.of(model, {}, None).current_bound is None


def test_train_reports_the_drive_range_and_its_bundle_carries_it(compose, tmp_path):
    store = write_store(tmp_path / "store", {"train": 300, "val": 60}, noise=0.01)
    with h5py.File(store / "dataset.h5", "r") as f:
        train_peaks = torch.as_tensor(f["train"]["current"][:]).abs().amax(1)
        val_peaks = torch.as_tensor(f["val"]["current"][:]).abs().amax(1)
    limit = float(train_peaks.quantile(0.9)) / 2.0
    _with_limit(store, limit)
    quick = ["n_modes=10", "n_points=16", "n_hidden=12", "eval.latency_repeats=20", "classifier_refine.rounds=0"]
    cfg = compose("train", [f"data_dir={store}", f"out_dir={tmp_path / 'out'}", *quick, "model.fit.max_epochs=5"])
    metrics, objects = train_surrogates(cfg)
    assert metrics["drive_current_bound"] == pytest.approx(2.0 * limit)
    assert metrics["n_train_beyond_drive_range"] == int((train_peaks > 2.0 * limit).sum()) > 0
    assert metrics["val_beyond_drive_range"] == int((val_peaks > 2.0 * limit).sum())
    assert 0.0 <= metrics["err_k_in_drive_range"] <= 1.0
    assert objects["bundle"].extra["drive_current_bound"] == pytest.approx(2.0 * limit)
