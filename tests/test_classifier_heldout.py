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
