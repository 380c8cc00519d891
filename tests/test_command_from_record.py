"""A bench's recorded command as a test command config (phm_torch.command.profile_from_samples and
scripts/command_from_record.py): every sample within the tolerance of the profile, few breakpoints where the command
is straight, a doublet's steps kept, and the YAML read back as any user command."""

from __future__ import annotations

import runpy
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from hydra.utils import instantiate

from phm_torch.command import Chirp, Profile, load_command_node, profile_from_samples, time_grid
from phm_torch.io.measurement_csv import write_measurement

SCRIPT = Path(__file__).resolve().parent.parent / "scripts" / "command_from_record.py"


@pytest.mark.parametrize("tolerance", [1e-5, 1e-6])
def test_a_sampled_chirp_is_kept_within_the_tolerance_on_few_breakpoints(tolerance):
    t = time_grid(0.5, 20_000.0)
    x = Chirp()(t)
    profile = profile_from_samples(t.numpy(), x.numpy(), tolerance)
    assert float((profile(t) - x).abs().max()) <= tolerance * (1 + 1e-9)
    assert len(profile.times) < 0.1 * t.numel()  # a 5 mrad chirp: 294 at 5e-6 (the script's default on it)
    coarser = profile_from_samples(t.numpy(), x.numpy(), 10 * tolerance)
    assert len(coarser.times) < len(profile.times)
    assert profile.duration == pytest.approx(0.5) and profile.times[0] == 0.0


def test_a_sampled_doublet_keeps_its_steps_and_nothing_else():
    doublet = Profile([0.0, 0.02, 0.02, 0.18, 0.18, 0.34, 0.34, 0.5], [0.0, 0.0, 4e-3, 4e-3, -4e-3, -4e-3, 0, 0], 0.5)
    t = time_grid(0.5, 20_000.0) + 1.25  # a record whose clock did not start at 0
    found = profile_from_samples(t.numpy(), doublet(t - 1.25).numpy(), 1e-6)
    assert len(found.times) == 8  # each step a one-sample ramp: the sample before it and the one at it
    torch.testing.assert_close(found(t - 1.25), doublet(t - 1.25), atol=1e-12, rtol=0)


def test_bad_samples_are_refused_by_name():
    t = np.linspace(0.0, 1.0, 11)
    with pytest.raises(ValueError, match="times must increase"):
        profile_from_samples(t[::-1], t, 1e-3)
    with pytest.raises(ValueError, match="tolerance must be > 0"):
        profile_from_samples(t, t, 0.0)
    with pytest.raises(ValueError, match="must be \\(n,\\) with n >= 2"):
        profile_from_samples(t, t[:5], 1e-3)


def test_the_script_writes_a_command_config_the_apps_read(tmp_path, monkeypatch, capsys):
    t = time_grid(0.5, 20_000.0)
    cmd = Chirp(amplitude=4e-3, f_end=10.0)(t)
    record = tmp_path / "healthy.csv"
    write_measurement(record, {"time": t, "command": cmd, "position": 0.9 * cmd, "current": 0.1 + 50 * cmd})
    out = tmp_path / "conf" / "command" / "my_test.yaml"
    monkeypatch.setattr(sys, "argv", ["x", "--record", str(record), "--out", str(out), "--tolerance", "1e-3"])
    with pytest.raises(SystemExit) as done:
        runpy.run_path(str(SCRIPT), run_name="__main__")
    assert done.value.code == 0 and "breakpoints of 10001 samples" in capsys.readouterr().out
    _, node = load_command_node(str(out))
    profile = instantiate(node)
    assert isinstance(profile, Profile) and float((profile(t) - cmd).abs().max()) <= 4e-6 * (1 + 1e-6)
    flat = tmp_path / "flat.csv"
    write_measurement(flat, {"time": t, "command": 0 * t, "position": 0 * t, "current": 0 * t + 0.1})
    monkeypatch.setattr(sys, "argv", ["x", "--record", str(flat), "--out", str(out)])
    with pytest.raises(SystemExit) as refused:
        runpy.run_path(str(SCRIPT), run_name="__main__")
    assert refused.value.code == 2 and "the command column is 0 throughout" in capsys.readouterr().err
