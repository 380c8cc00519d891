"""scripts/fdi_timing_tolerance.py: a bundle's reading of the store's val records moved in time; on time it is the
bundle's own reading (no move, its own err_k), moved it is another."""

from __future__ import annotations

import json

import torch
from script_module import script_module
from surrogate_data import write_store

from phm_torch.data import DatasetStore
from phm_torch.faults import FAULT_NAMES
from phm_torch.surrogates import FDIMLP, POD, GappyPOD, SurrogateBundle
from phm_torch.surrogates.classifiers import MLPClassifier


def test_the_script_reads_each_bundle_on_time_and_moved(tmp_path):
    store = write_store(tmp_path / "store", {"train": 60, "val": 25})
    with DatasetStore(store) as s:
        x = torch.as_tensor(s.split("train").current[()], dtype=torch.float32)
        k = torch.as_tensor(s.split("train").K[()], dtype=torch.float32)
        healthy = torch.as_tensor(s.split("train").healthy[()]).bool()
    torch.manual_seed(0)
    pod = POD(6).fit(x)
    indices = torch.arange(3, x.shape[1], max(1, x.shape[1] // 40))
    gappy = GappyPOD(pod.modes_, pod.mean_, indices)
    network = FDIMLP(6, 8).set_normalization(gappy(gappy.select(x))[0])
    classifier = MLPClassifier(hidden=[8], epochs=3, seed=0).fit(k, healthy)
    path = SurrogateBundle(pod, indices, network, classifier, 20000.0).save(tmp_path / "surrogates.pt")
    out = tmp_path / "timing.json"
    report = script_module("fdi_timing_tolerance").main(
        ["--data-dir", str(store), "--bundle", str(path), "--shifts", "0", "5", "--out", str(out)]
    )
    assert json.loads(out.read_text()) == json.loads(json.dumps(report))
    assert report["records"] == 25 and report["shifts_samples"] == [0, 5]
    figures = report["bundles"][str(path)]
    assert set(figures) == {"0", "5"} and set(figures["0"]["k_hat_mean_move"]) == set(FAULT_NAMES)
    assert all(v == 0.0 for v in figures["0"]["k_hat_mean_move"].values())  # on time: the reading itself
    assert any(abs(v) > 1e-6 for v in figures["5"]["k_hat_mean_move"].values())
    assert figures["0"]["n"] == figures["5"]["n"] == 25 and 0.0 <= figures["5"]["chain_accuracy"] <= 1.0
