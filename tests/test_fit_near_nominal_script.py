"""scripts/fit_near_nominal.py end to end on a small synthetic life split: the whole-record network it writes loads,
belongs to the pipeline, reads the records on its own basis, is calibrated and learned the damages; a bad width
factor is refused (exit status 2, naming the value)."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest
import torch
from test_tracking import N_FULL, damage_config, make_pipeline

from phm_torch.io import write_measurement
from phm_torch.online.export import export_torchscript
from phm_torch.online.loaded import load_pipeline
from phm_torch.tracking.near_nominal import NearNominalFDI

ROOT = Path(__file__).resolve().parents[1]
SCRIPT = ROOT / "scripts" / "fit_near_nominal.py"


def life_split(root: Path, pipe, n_actuators: int = 30, n_inspections: int = 12) -> None:
    """Histories whose records are the pipeline's mean signal plus its modes times a linear function of small
    damages, at 1 % noise: the truth.json / CSV layout of a life split."""
    g = torch.Generator().manual_seed(1)
    mix = 5.0 * torch.randn(6, pipe.modes.shape[1], generator=g, dtype=torch.float64)  # well above the noise
    actuators = {}
    for a in range(n_actuators):
        inspections = []
        for i in range(n_inspections):
            k = torch.tensor([0.0] * 6 + [0.5, 0.5], dtype=torch.float64)
            k[:6] = 0.2 * torch.rand(6, generator=g, dtype=torch.float64)
            current = pipe.mean_signal + pipe.modes @ (k[:6] @ mix)
            current = current + 0.01 * current.pow(2).mean().sqrt() * torch.randn(N_FULL, generator=g)
            name = f"A{a:02d}/{i:04d}.csv"
            zeros = torch.zeros(N_FULL, dtype=torch.float64)
            time = torch.arange(N_FULL, dtype=torch.float64) / 20000.0
            write_measurement(root / name, {"time": time, "command": zeros, "position": zeros, "current": current})
            inspections.append({"hours": 200.0 * i, "file": name, "k_true": k.tolist()})
        actuators[f"A{a:02d}"] = {"inspections": inspections}
    (root / "truth.json").write_text(json.dumps({"actuators": actuators}))


def run_script(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, str(SCRIPT), *args], check=False, capture_output=True, text=True, timeout=600
    )


@pytest.mark.slow  # trains a network; ~55 s
@pytest.mark.torchscript
def test_the_script_fits_a_calibrated_whole_record_network(tmp_path):
    pipe = make_pipeline()
    export_torchscript(pipe, tmp_path / "online.pt", {"damage": damage_config()})
    life_split(tmp_path / "life", pipe)
    out = tmp_path / "online.near_nominal.pt"
    common = ["--pipeline", str(tmp_path / "online.pt"), "--life", str(tmp_path / "life"), "--out", str(out)]
    done = run_script(
        *common,
        *("--full-record", "8", "--steps", "3000", "--gate", "1.0", "--noise-levels", "0.01,0.02"),
        *("--width-factor", "1.25", "--threads", "1"),
    )
    assert done.returncode == 0, done.stderr[-2000:]
    report = json.loads(done.stdout)
    near = NearNominalFDI.load(out)
    module = load_pipeline(tmp_path / "online.pt").module
    near.check_for(module, "the synthetic pipeline")
    assert near.n_full == N_FULL and report["input"] == "full record, 8 principal directions"
    assert report["calibration_actuators"] == 6 and report["calibration_records"] == 72  # every 5th of 30
    assert 0.0 < report["basis_variance_fraction"] < 1.0  # of signal and noise together
    # its leading directions lie in the span of the six modes the damages move, not in the noise's
    inside = (pipe.modes.T @ near.basis_.double()).pow(2).sum(0).sqrt()
    assert float(inside[:4].min()) > 0.95
    rms = torch.tensor([report["heldout"]["0.01"]["rms"][n] for n in ("dry_friction", "backlash", "short_a")])
    assert float(rms.max()) < 0.5 * 0.2 / 12**0.5, rms  # half the spread of the truth: it learned the damages
    # the file's half-widths are the held-out rms widened by the factor
    expected = 1.25 * 1.6448536269514722 * rms
    assert torch.allclose(near.half_widths_[0, :3], expected.double(), rtol=1e-6)
    refused = run_script(*common, "--width-factor", "0.5")
    assert refused.returncode == 2 and "--width-factor must be >= 1, got 0.5" in refused.stderr
