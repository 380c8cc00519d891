"""phm_torch/report/figure_uncertainty.py and compare_actuators --bootstrap: the figures' sampling intervals."""

from __future__ import annotations

import json
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from phm_torch.prognostics.evaluation import RULComparison
from phm_torch.report.figure_uncertainty import interval, proportion_draws, ratio_status, run_figure_draws
from phm_torch.surrogates.metrics import err_k

SCRIPT = Path(__file__).resolve().parents[1] / "scripts" / "compare_actuators.py"


def _write_run(root: Path, n_val: int, n_rul: int, error: float, seed: int) -> dict[str, torch.Tensor]:
    """A run directory's per-record files: val estimates off by Gaussian errors of std ``error``, healthy where
    k1 < 0.5 (the verdict right on 90 %), and RULs from true k / the full flow off by 2 % / 30 % (lognormal)."""
    gen = torch.Generator().manual_seed(seed)
    k = torch.rand(n_val, 8, generator=gen, dtype=torch.float64)
    k_hat = k + error * torch.randn(n_val, 8, generator=gen, dtype=torch.float64)
    healthy = k[:, 0] < 0.5
    flip = torch.rand(n_val, generator=gen) < 0.1
    said = healthy ^ flip
    arrays = {
        "k": k,
        "k_hat": k_hat,
        "err_alpha": torch.rand(n_val, generator=gen, dtype=torch.float64) * 0.2,
        "healthy": healthy,
        "score": torch.where(healthy, 1.0, -1.0).double(),
        "score_chain": torch.where(said, 1.0, -1.0).double(),
    }
    (root / "train").mkdir(parents=True)
    (root / "evaluate").mkdir()
    torch.save(arrays, root / "train" / "predictions.pt")
    ref50 = 1000 + 1000 * torch.rand(n_rul, generator=gen, dtype=torch.float64)
    ref = torch.stack([0.8 * ref50, ref50, 1.2 * ref50], 1)
    ref[:3] = 0  # three vectors faulty already: left out of the relative errors
    true_k = ref * torch.exp(0.02 * torch.randn(n_rul, 1, generator=gen, dtype=torch.float64))
    flow = ref * torch.exp(0.3 * torch.randn(n_rul, 1, generator=gen, dtype=torch.float64))
    flow[5] = -1.0  # a full flow that did not answer
    predictions = {"reference": ref.tolist(), "true_k": true_k.tolist(), "full_flow": flow.tolist()}
    (root / "evaluate" / "rul_predictions.json").write_text(json.dumps(predictions))
    return {**arrays, "ref": ref, "true_k": true_k, "flow": flow}


def test_the_draws_recompute_each_figure_and_narrow_as_the_split_grows(tmp_path):
    small = _write_run(tmp_path / "small", 100, 100, 0.1, 1)
    _write_run(tmp_path / "large", 1600, 1600, 0.1, 2)
    d_small = run_figure_draws(tmp_path / "small", draws=400, seed=0)
    d_large = run_figure_draws(tmp_path / "large", draws=400, seed=0)
    exact = err_k(small["k_hat"], small["k"])
    lo, hi = interval(d_small["err_k"])
    assert lo < exact < hi and abs(float(np.median(d_small["err_k"])) - exact) < 0.1 * exact
    # the verdict is wrong on a tenth of the records: its accuracy's draws scatter like a binomial of 100
    assert float(np.std(d_small["verdict_accuracy"])) == pytest.approx(math.sqrt(0.9 * 0.1 / 100), rel=0.35)
    flow = small["flow"].clone()
    flow[flow < 0] = math.nan  # -1 in the file: no answer, left out as the evaluation leaves it out
    full = RULComparison(small["ref"], small["true_k"], flow).metrics()
    for name in ("rul_err_median_true_k", "rul_err_median_full_flow", "rul_band_coverage_full_flow"):
        lo, hi = interval(d_small[name])
        assert lo <= full[name] <= hi, name
    # the bands hold every truth (true k off by 2 %, bands of +-20 %): 97 of 97, an interval below 1 all the same
    assert full["rul_band_coverage_true_k"] == 1.0
    assert 0.95 < interval(d_small["rul_band_coverage_true_k"])[0] < 0.995
    # 16 times the records: intervals about 4 times narrower
    for name in ("err_k", "verdict_accuracy", "rul_err_median_full_flow"):
        width = [np.subtract(*interval(d)[::-1]) for d in (d_small[name], d_large[name])]
        assert 2.5 < width[0] / width[1] < 6.5, (name, width)
    # the health classifier's score is the labels themselves: 100 of 100, Jeffreys' 95 % lower bound 0.975
    assert 0.97 < interval(d_small["classifier_accuracy"])[0] < 0.98
    with pytest.raises(ValueError, match="draws must be >= 100"):
        run_figure_draws(tmp_path / "small", draws=10)


def test_a_proportion_spreads_as_a_binomial_and_a_ratio_is_decided_only_clear_of_the_factor():
    draws = proportion_draws(30, 200, draws=4000, seed=3)
    assert float(draws.mean()) == pytest.approx(30.5 / 201, abs=0.003)  # the Beta(30.5, 170.5) mean
    assert float(draws.std()) == pytest.approx(math.sqrt(0.15 * 0.85 / 200), rel=0.06)  # a binomial's spread
    with pytest.raises(ValueError, match="0 <= successes <= n"):
        proportion_draws(5, 4)
    rng = np.random.default_rng(0)
    base = rng.normal(0.10, 0.002, 2000)
    assert ratio_status(base, rng.normal(0.16, 0.002, 2000), True, 1.3)["status"] == "outside"
    assert ratio_status(base, rng.normal(0.11, 0.002, 2000), True, 1.3)["status"] == "within"
    wide = ratio_status(base, rng.normal(0.13, 0.02, 2000), True, 1.3)
    assert wide["status"] == "undecided" and wide["ratio_lo"] < 1.3 < wide["ratio_hi"]
    # an accuracy: at least 1 / 1.3 of the base's
    assert ratio_status(base, rng.normal(0.06, 0.002, 2000), False, 1.3)["status"] == "outside"
    assert ratio_status(base, rng.normal(0.09, 0.002, 2000), False, 1.3)["status"] == "within"
    with pytest.raises(ValueError, match="factor must be >= 1"):
        ratio_status(base, base, True, 0.5)


def test_compare_actuators_reports_each_ratios_interval_and_status(tmp_path):
    written = {}
    for name, error in (("reference", 0.1), ("other", 0.3)):
        written[name] = _write_run(tmp_path / name, 400, 100, error, 7 if name == "reference" else 8)
        (tmp_path / name / "data").mkdir()
        (tmp_path / name / "data" / "manifest.json").write_text(
            json.dumps({"splits": {"train": {"count": 100, "healthy": 30}}})
        )
        for stage in ("train", "evaluate"):
            (tmp_path / name / stage / "metrics.json").write_text(json.dumps({"err_k": error * 1.1}))
    bench = {"summary": {"effects": 6, "hit_rate": 5 / 6}}
    (tmp_path / "bench.json").write_text(json.dumps(bench))
    out = tmp_path / "cmp.json"
    args = ["--run", f"reference={tmp_path / 'reference'}", "--run", f"other={tmp_path / 'other'}"]
    args += ["--workbench", f"reference={tmp_path / 'bench.json'}", "--workbench", f"other={tmp_path / 'bench.json'}"]
    done = subprocess.run(
        [sys.executable, str(SCRIPT), *args, "--bootstrap", "300", "--out", str(out)],
        check=True,
        capture_output=True,
        text=True,
    )
    result = json.loads(out.read_text())
    rows = result["verdicts"]["other"]
    assert rows["err_k"]["status"] == "outside" and rows["err_k"]["ratio_lo"] > 2.5  # three times the error
    assert rows["workbench_hit_rate"]["status"] == "undecided"  # 5 of 6 against 5 of 6: six cases decide nothing
    assert "(outside)" in done.stdout and result["bootstrap"] == 300
    tally = result["status_tally"]["other"]
    assert sum(tally.values()) == 11 and tally["outside"] >= 1 and tally["undecided"] >= 1  # 13 less LF and healthy
    lo, hi = result["intervals"]["reference"]["err_k"]
    assert lo < err_k(written["reference"]["k_hat"], written["reference"]["k"]) < hi
    bad = subprocess.run(
        [sys.executable, str(SCRIPT), *args, "--bootstrap", "20"], capture_output=True, text=True, check=False
    )
    assert bad.returncode != 0 and "--bootstrap must be 0 or >= 100, got 20" in bad.stderr
