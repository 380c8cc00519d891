"""scripts/fdi_capacity_probe.py: an FDI on whole-record POD coefficients reads what the records carry, and fewer modes
read less (the synthetic store's records are an invertible function of k on 10 modes)."""

from __future__ import annotations

import pytest
import surrogate_data
from script_module import script_module


@pytest.fixture(scope="module")
def store(tmp_path_factory):
    return surrogate_data.write_store(tmp_path_factory.mktemp("probe"), {"train": 800, "val": 150}, seed=2)


def test_enough_modes_read_every_component_and_two_modes_do_not(store, tmp_path):
    script = script_module("fdi_capacity_probe")
    base = ["--data-dir", str(store), "--hidden", "64", "--epochs", "80", "--threads", "1"]
    full = script.main([*base, "--modes", "10", "--out", str(tmp_path / "full.json")])
    assert full["energy_held"] == pytest.approx(1.0, abs=1e-6) and full["records"]["beyond_drive_range"] == 0
    assert min(full["r2"].values()) > 0.8 and full["err_k"] < 0.06
    two = script.main([*base, "--modes", "2", "--out", str(tmp_path / "two.json")])
    assert two["energy_held"] < 0.95 and two["err_k"] > 2 * full["err_k"]
    assert sum(r < 0.2 for r in two["r2"].values()) >= 5  # only the two leading latents read


def test_bad_arguments_and_a_store_without_val_are_refused(tmp_path):
    script = script_module("fdi_capacity_probe")
    only_train = surrogate_data.write_store(tmp_path / "s", {"train": 50})
    with pytest.raises(ValueError, match="--modes, --hidden and --epochs must be >= 1, got 0"):
        script.main(["--data-dir", str(only_train), "--modes", "0", "--out", str(tmp_path / "a.json")])
    with pytest.raises(ValueError, match="has no 'val' split"):
        script.main(["--data-dir", str(only_train), "--out", str(tmp_path / "a.json")])
