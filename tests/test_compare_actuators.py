"""scripts/compare_actuators.py: figures side by side from run directories and from an earlier comparison."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

SCRIPT = Path(__file__).resolve().parents[1] / "scripts" / "compare_actuators.py"


def _run_dir(root: Path, err_k: float, crossings: dict | None = None) -> Path:
    for sub in ("train", "evaluate", "data"):
        (root / sub).mkdir(parents=True)
    train = {"err_alpha_median": 0.02, "err_k": err_k, "classifier_accuracy": 0.99, "missed_fault_rate": 0.01}
    train.update(chain_accuracy=0.9, chain_missed_fault_rate=0.05, actuator="rudder (sha256 0)")
    (root / "train" / "metrics.json").write_text(json.dumps(train))
    evaluate = {"rul_err_median_true_k": 0.01, **(crossings or {})}
    (root / "evaluate" / "metrics.json").write_text(json.dumps(evaluate))
    (root / "data" / "manifest.json").write_text(json.dumps({"splits": {"train": {"count": 100, "healthy": 30}}}))
    return root


def test_figures_of_an_earlier_comparison_fill_what_a_run_lacks(tmp_path):
    earlier = {
        "figures": {
            "reference": {"err_k": 0.10, "hf_lf_current_nrmse_median": 0.02, "workbench_hit_rate": 0.8},
            "rudder": {"err_k": 0.30, "hf_lf_current_nrmse_median": 0.022, "workbench_hit_rate": 0.7},
        }
    }
    (tmp_path / "earlier.json").write_text(json.dumps(earlier))
    run = _run_dir(tmp_path / "rudder_run", err_k=0.12)
    out = tmp_path / "cmp.json"
    args = ["--run", f"rudder={run}", "--figures", f"reference={tmp_path / 'earlier.json'}"]
    args += ["--figures", f"rudder={tmp_path / 'earlier.json'}", "--out", str(out)]
    subprocess.run([sys.executable, str(SCRIPT), *args], check=True, capture_output=True, text=True)
    done = json.loads(out.read_text())
    assert list(done["figures"]) == ["reference", "rudder"]  # the --figures names first: the base
    rudder = done["figures"]["rudder"]
    assert rudder["err_k"] == 0.12 and rudder["hf_lf_current_nrmse_median"] == 0.022  # the run's, else the earlier
    assert rudder["healthy_fraction_train"] == 0.3
    verdicts = done["verdicts"]["rudder"]
    assert abs(verdicts["err_k"]["ratio"] - 1.2) < 1e-12 and verdicts["err_k"]["met"] is True
    assert verdicts["workbench_hit_rate"]["met"] is True and verdicts["hf_lf_current_nrmse_median"]["met"] is True
    bad = subprocess.run(
        [sys.executable, str(SCRIPT), "--run", f"rudder={run}", "--figures", f"trim={tmp_path / 'earlier.json'}"],
        capture_output=True,
        text=True,
        check=False,
    )
    assert bad.returncode != 0 and "holds no figures of 'trim'" in bad.stderr


def test_the_classifier_figures_of_a_held_out_report_replace_the_val_splits(tmp_path):
    base = _run_dir(tmp_path / "reference_run", err_k=0.10)
    run = _run_dir(tmp_path / "rudder_run", err_k=0.12)
    report = {"accuracy": 0.98, "missed_fault_rate": 0.011}
    (tmp_path / "heldout.json").write_text(json.dumps(report))
    out = tmp_path / "cmp.json"
    args = ["--run", f"reference={base}", "--run", f"rudder={run}"]
    args += ["--classifier-heldout", f"rudder={tmp_path / 'heldout.json'}", "--out", str(out)]
    subprocess.run([sys.executable, str(SCRIPT), *args], check=True, capture_output=True, text=True)
    done = json.loads(out.read_text())
    assert done["figures"]["rudder"]["classifier_missed_fault_rate"] == 0.011
    assert done["figures"]["rudder"]["classifier_accuracy"] == 0.98
    assert done["figures"]["reference"]["classifier_missed_fault_rate"] == 0.01  # its run's own (val)
    assert abs(done["verdicts"]["rudder"]["classifier_missed_fault_rate"]["ratio"] - 1.1) < 1e-12
    assert done["classifier_from"] == {"rudder": str(tmp_path / "heldout.json")}
    bad = subprocess.run(
        [
            sys.executable,
            str(SCRIPT),
            "--run",
            f"rudder={run}",
            "--classifier-heldout",
            f"x={tmp_path / 'heldout.json'}",
        ],
        capture_output=True,
        text=True,
        check=False,
    )
    assert bad.returncode != 0 and "--classifier-heldout needs a --run of ['x']" in bad.stderr


def test_the_reference_crossings_of_each_run_are_reported_beside_the_figures(tmp_path):
    """A run evaluated with the crossing counts gets its line and JSON entry; one evaluated before them gets none."""
    counts = {
        "rul_reference_crossings": 138,
        "rul_reference_jump_crossings": 59,
        "rul_err_median_true_k_smooth": 0.0183,
        "rul_err_median_true_k_jump": 0.0929,
    }
    base = _run_dir(tmp_path / "reference_run", err_k=0.10)
    run = _run_dir(tmp_path / "flap_run", err_k=0.11, crossings=counts)
    out = tmp_path / "cmp.json"
    args = ["--run", f"reference={base}", "--run", f"flap={run}", "--out", str(out)]
    done = subprocess.run([sys.executable, str(SCRIPT), *args], check=True, capture_output=True, text=True)
    assert (
        "flap: 59 of 138 reference crossings jump; RUL from the true k 1.83 % on the smooth ones, 9.29 % on the jumps"
        in done.stdout
    )
    assert json.loads(out.read_text())["crossings"] == {"flap": counts}
