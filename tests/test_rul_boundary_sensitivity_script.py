"""scripts/rul_boundary_sensitivity.py: how far the reference RUL moves when the health boundary moves."""

from __future__ import annotations

import math

import pytest
import torch
from script_module import script_module

from phm_torch.prognostics.damage import DamageModel
from phm_torch.prognostics.reference import reference_rul

RATE = 1e-3  # [1/h]: dk1/dt = RATE * (k1 - 0), so k1(t) = k1(0) exp(RATE t)


def _setup() -> tuple[DamageModel, torch.Tensor]:
    rate = [[0.0] * 8 for _ in range(8)]
    rate[0][0] = RATE
    damage = DamageModel(rate, [1e-6] + [0.0] * 7, 100.0, 20000.0, 50.0, [0, 0, 0, 0, 0, 0, 0.5, 0.5])
    k = torch.tensor([[k1, 0, 0, 0, 0, 0, 0.5, 0.5] for k1 in (0.1, 0.2, 0.3, 0.7)], dtype=torch.float64)
    return damage, k


def test_a_stricter_boundary_shortens_the_rul_as_the_exponential_growth_says():
    """Healthy while the friction damage is below 0.6: the RUL is ln(0.6 / k1) / RATE, and 1 % of margin
    stricter (0.59) shortens it to ln(0.59 / k1) / RATE; a vector already past the boundary is left out."""
    script = script_module("rul_boundary_sensitivity")
    damage, k = _setup()

    def score(x: torch.Tensor) -> torch.Tensor:
        return 0.6 - x[:, 0]

    deltas = torch.zeros(3, dtype=torch.float64)
    base = reference_rul(damage, score, k, deltas, 500.0, 10)
    assert base[0, 1] == pytest.approx(math.log(6.0) / RATE, rel=2e-3) and base[3, 1] == 0
    figures = script.boundary_sensitivity(damage, score, k, deltas, base, 0.01, 500.0, 10)
    # three usable vectors: the median is the middle one, k1 = 0.2 (-1.5 %; 0.1 gives -0.9 %, 0.3 gives -2.4 %)
    assert figures["usable"] == 3
    expected = math.log(0.59 / 0.2) / math.log(0.6 / 0.2) - 1
    assert figures["median_rel_change"] == pytest.approx(expected, rel=0.05)
    assert figures["median_abs_rel_change"] == pytest.approx(-figures["median_rel_change"])
    with pytest.raises(ValueError, match="eps must be in"):
        script.boundary_sensitivity(damage, score, k, deltas, base, 0.0, 500.0, 10)


def test_a_run_without_its_cached_reference_is_refused(tmp_path):
    script = script_module("rul_boundary_sensitivity")
    with pytest.raises(SystemExit, match="no cached reference RUL"):
        script.main(["--run", str(tmp_path)])
