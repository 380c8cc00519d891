"""scripts/classifier_heldout.py: a bundle's health classifier judged on another store's labels, never its own."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import torch
from surrogate_data import health, write_store

from phm_torch.data.store import read_labelled
from phm_torch.surrogates import POD, SurrogateBundle
from phm_torch.surrogates.classifiers.polynomial_svm import PolynomialSVM
from phm_torch.surrogates.data import load_store
from phm_torch.surrogates.fdi_mlp import FDIMLP

SCRIPT = Path(__file__).resolve().parents[1] / "scripts" / "classifier_heldout.py"


def test_counts_on_an_independent_store_and_refuses_the_training_store(tmp_path):
    trained = write_store(tmp_path / "trained", {"train": 300}, seed=0)
    heldout = write_store(tmp_path / "heldout", {"labels": 400}, seed=5)
    data, _, _ = load_store(str(trained), {"train": "train"}, {})
    pod = POD(6).fit(data["train"].current)
    classifier = PolynomialSVM(degree=1).fit(data["train"].k, data["train"].healthy)  # a linear one: it errs
    bundle = SurrogateBundle(pod, torch.arange(0, 24, 2), FDIMLP(6, 5), classifier, 20000.0)
    bundle.extra["data_fingerprint"] = "test-0"  # write_store's fingerprint of the training store
    bundle.save(tmp_path / "b.pt")
    out = tmp_path / "heldout.json"
    run = [sys.executable, str(SCRIPT), "--bundle", str(tmp_path / "b.pt"), "--out", str(out)]
    subprocess.run([*run, "--data-dir", str(heldout)], check=True, capture_output=True, text=True)
    report = json.loads(out.read_text())
    k, healthy = read_labelled(heldout, ("labels",), ())
    k, truth = torch.as_tensor(k), torch.as_tensor(healthy).bool()
    assert torch.equal(truth, health(k).bool())
    pred = classifier.predict(k)
    assert report["n"] == 400 and report["faulty"] == int((~truth).sum())
    assert report["missed"] == int((pred & ~truth).sum()) and report["false_alarms"] == int((~pred & truth).sum())
    assert 0 < report["missed"] + report["false_alarms"] < 400  # a classifier that errs, counted
    assert report["accuracy"] == (400 - report["missed"] - report["false_alarms"]) / 400
    refused = subprocess.run([*run, "--data-dir", str(trained)], check=False, capture_output=True, text=True)
    assert refused.returncode != 0 and "is the one the bundle was trained on" in refused.stderr
    # assessing the errors again needs the store's own assessment config; this store (not phm-generate's) has none
    again = subprocess.run(
        [*run, "--data-dir", str(heldout), "--uncertain", "5"], check=False, capture_output=True, text=True
    )
    assert again.returncode != 0 and "does not record the actuator and assessment config" in again.stderr
    assert "Traceback" not in again.stderr


def test_a_store_of_another_actuator_is_refused_in_one_line(tmp_path):
    import h5py

    from phm_torch import provenance
    from phm_torch.params import load_actuator

    heldout = write_store(tmp_path / "heldout", {"labels": 50}, seed=5)
    chirp = {"_target_": "phm_torch.command.Chirp", "amplitude": 5e-3, "f_start": 0.0, "f_end": 15.0, "duration": 0.5}
    command = provenance.command_record("chirp", chirp)
    with h5py.File(heldout / "dataset.h5", "r+") as f:  # the store says which actuator it was made for
        meta = json.loads(f.attrs["metadata"])
        meta["provenance"] = {
            "actuator": provenance.actuator_record("ema_reference", load_actuator()),
            "command": command,
        }
        f.attrs["metadata"] = json.dumps(meta)
    trained = write_store(tmp_path / "trained", {"train": 100}, seed=0)
    data, _, _ = load_store(str(trained), {"train": "train"}, {})
    pod = POD(4).fit(data["train"].current)
    classifier = PolynomialSVM(degree=1).fit(data["train"].k, data["train"].healthy)
    bundle = SurrogateBundle(pod, torch.arange(0, 12, 2), FDIMLP(4, 5), classifier, 20000.0)
    rudder = provenance.actuator_record("ema_hvdc_rudder", load_actuator("ema_hvdc_rudder"))
    bundle.extra["provenance"] = {"actuator": rudder, "command": command}
    bundle.save(tmp_path / "b.pt")
    run = [sys.executable, str(SCRIPT), "--bundle", str(tmp_path / "b.pt"), "--data-dir", str(heldout)]
    refused = subprocess.run(run, check=False, capture_output=True, text=True)
    assert refused.returncode != 0
    assert refused.stderr.strip().splitlines()[-1].startswith("classifier_heldout: error: actuator=ema_hvdc_rudder")
    assert "Traceback" not in refused.stderr
