"""scripts/assess.py: the health label phi_a gives fault vectors, the truth to judge phm-predict's verdicts against."""

from __future__ import annotations

import json

import pytest
from script_module import script_module


@pytest.mark.slow  # the shipped sweep on several vectors; ~40 s
def test_labels_from_the_command_line_and_a_csv_with_the_shipped_assessment(tmp_path, capsys):
    """A short in phase B at 0.98 fails (bandwidth ~22 Hz against ~76); in phase A it reads the nominal margins at
    one rotor position and fails at the shipped three; a CSV by fault names reads the same; bad vectors are refused
    by name."""
    script = script_module("assess")
    assert script.main(["--faults", "0,0,0,0.98,0,0,0.5,0.5", "0,0,0.98,0,0,0,0.5,0.5", "--rotor-positions", "1"]) == 0
    b, a = (json.loads(line) for line in capsys.readouterr().out.splitlines())
    assert not b["healthy"] and b["bandwidth_hz"] == pytest.approx(22.1, abs=1.0)
    assert a["healthy"] and a["bandwidth_hz"] == pytest.approx(75.9, abs=1.0)
    csv = tmp_path / "v.csv"
    names = "dry_friction,backlash,short_a,short_b,short_c,eccentricity,eccentricity_phase,gain_drift"
    csv.write_text(f"{names}\n0,0,0.98,0,0,0,0.5,0.5\n")
    assert script.main(["--csv", str(csv)]) == 0
    (three,) = (json.loads(line) for line in capsys.readouterr().out.splitlines())
    assert not three["healthy"] and three["bandwidth_hz"] == pytest.approx(b["bandwidth_hz"], rel=1e-6)
    with pytest.raises(ValueError, match="has 3 values, not 8"):
        script.main(["--faults", "0,0,2"])
    with pytest.raises(ValueError, match=r"entry|outside|\[0, 1\]"):
        script.main(["--faults", "0,0,2,0,0,0,0.5,0.5"])
