"""phm_torch.surrogates.compare (scripts/rank_bundles.py's statistics): err_k, its bootstrap interval and paired
differences from per-signal errors; the verdict's confusion and McNemar test."""

from __future__ import annotations

import pytest
import torch

from phm_torch.surrogates import compare


@pytest.fixture(scope="module")
def script():
    return compare


@pytest.fixture(scope="module")
def rank(script):
    return script.ranking


def test_verdict_table_counts_and_mcnemar(script):
    from scipy.stats import binomtest

    healthy = torch.tensor([True] * 40 + [False] * 60)
    a = healthy.clone()
    a[:5] = False  # a: 5 false alarms
    a[40:52] = True  # and 12 missed faults
    b = healthy.clone()
    b[40:43] = True  # b: 3 missed faults (right on 9 records a gets wrong)
    b[90:92] = True  # and 2 missed faults that a gets right
    b[:5] = False  # the same 5 false alarms
    out = script.verdict_table({"a": a, "b": b}, healthy)
    assert out["a"]["accuracy"] == pytest.approx(0.83) and out["a"]["missed_fault_rate"] == pytest.approx(12 / 60)
    assert out["a"]["false_alarm_rate"] == pytest.approx(5 / 40) and "mcnemar_p" not in out["a"]
    assert out["b"]["accuracy"] == pytest.approx(0.90) and out["b"]["missed_fault_rate"] == pytest.approx(5 / 60)
    assert (out["b"]["only_a"], out["b"]["only_this"]) == (2, 9)
    assert out["b"]["mcnemar_p"] == pytest.approx(binomtest(2, 11, 0.5).pvalue)
    assert script.mcnemar_p(0, 0) == 1.0 and script.mcnemar_p(10, 0) == pytest.approx(2 / 1024)


def test_ranking_of_a_uniformly_better_bundle(rank):
    g = torch.Generator().manual_seed(0)
    counts = torch.randint(0, 4, (3000,), generator=g)
    base = (0.01 + 0.05 * counts.double()) * torch.rand(3000, generator=g, dtype=torch.float64)
    sq = {"a": base.pow(2), "b": (0.9 * base).pow(2)}  # b: every signal's error 10 % smaller
    out = rank(sq, counts, seed=1)
    err_a = float(base.pow(2).mean().sqrt())
    assert out["n"] == 3000 and out["a"]["err_k_pct"] == pytest.approx(100 * err_a)
    assert out["b"]["err_k_pct"] == pytest.approx(90 * err_a)
    lo, hi = out["a"]["ci95_pct"]
    assert lo < 100 * err_a < hi and hi - lo < 0.2 * 100 * err_a
    # paired: the shared spread cancels, so the difference is -10 % of each resample's err_k, a tight interval
    d_lo, d_mid, d_hi = out["b"]["minus_a_pp"]
    assert d_lo < d_mid < d_hi < 0 and d_mid == pytest.approx(-10 * err_a, rel=0.02)
    assert d_hi - d_lo < 0.5 * (hi - lo)
    by_group = out["a"]["err_k_by_heavy_faults_pct"]
    assert by_group["0"] < by_group["1"] < by_group["2"] < by_group["3+"]
    assert sum(out["group_share"].values()) == pytest.approx(1.0)


def test_bundle_specs_name_the_bundles(tmp_path, monkeypatch):
    from phm_torch.surrogates import bundle_specs as bundle_module

    monkeypatch.setattr(bundle_module.SurrogateBundle, "load", classmethod(lambda cls, path: f"loaded {path}"))
    sweep = "multirun/0/n_hidden=20/surrogates.pt"  # a Hydra sweep's path keeps its '='
    got = bundle_module.load_named_bundles(["a=x.pt", "y.pt", f"b={sweep}", sweep])
    assert got == {"a": "loaded x.pt", "bundle1": "loaded y.pt", "b": f"loaded {sweep}", "bundle3": f"loaded {sweep}"}
    assert bundle_module.load_named_bundles(["only.pt"]) == {"bundle": "loaded only.pt"}
    with pytest.raises(ValueError, match="'a' is given twice"):
        bundle_module.load_named_bundles(["a=x.pt", "a=y.pt"])
