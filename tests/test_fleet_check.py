"""The fleet check (phm_torch.tracking.fleet_check): a damage vector that every actuator's first inspection reads is
a bench or model difference, not wear; a fleet of new actuators or of used ones each with its own damage is not
flagged."""

from __future__ import annotations

import numpy as np
import pytest

from phm_torch.faults import FAULT_NAMES
from phm_torch.tracking.fleet_check import FleetCheckSettings, check_fleet

NOMINAL = [0.0] * 6 + [0.5, 0.5]
HALF = 0.006  # calibrated 90 % half-width of each estimate


def first_inspections(k_hat: np.ndarray, ood: int = 0) -> list[dict]:
    out = []
    for i, row in enumerate(k_hat):
        out.append(
            {
                "k_hat": dict(zip(FAULT_NAMES, row.tolist())),
                "k_interval": {n: [v - HALF, v + HALF] for n, v in zip(FAULT_NAMES, row.tolist())},
                "out_of_distribution": i < ood,
            }
        )
    return out


def fleet(n: int, offset: np.ndarray | None = None, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    k = np.tile(np.array(NOMINAL), (n, 1))
    k[:, :6] += rng.uniform(0.0, 0.01, (n, 6))  # each actuator's small initial damage
    k[:, :6] += rng.normal(0.0, HALF / 1.645, (n, 6))  # the estimate's error
    k[:, 6] = rng.uniform(0, 1, n)  # the phase: anything
    return k + (0.0 if offset is None else offset)


def test_a_new_fleet_is_not_flagged_and_a_common_offset_is():
    settings = FleetCheckSettings()
    clean = check_fleet(first_inspections(fleet(40)), NOMINAL, settings)
    assert clean["checked"] and not clean["offset"] and clean["message"] is None
    shift = np.zeros(8)
    shift[[0, 2, 3, 4]] = 0.022  # warmer windings: friction and the three shorts, as measured
    found = check_fleet(first_inspections(fleet(40, shift)), NOMINAL, settings)
    assert found["offset"] and set(found["components"]) == {"dry_friction", "short_a", "short_b", "short_c"}
    assert found["components"]["short_b"]["median"] == pytest.approx(0.027, abs=0.003)
    assert "give baseline=" in found["message"] and "\n" not in found["message"]
    # a component the command does not identify reads the training prior everywhere: not an offset
    prior = fleet(40)
    prior[:, 5] = 0.1
    firsts = [{**d, "k_not_identified": ["eccentricity"]} for d in first_inspections(prior)]
    assert check_fleet(first_inspections(prior), NOMINAL, settings)["offset"]
    assert not check_fleet(firsts, NOMINAL, settings)["offset"]


def test_used_actuators_each_with_its_own_damage_do_not_agree_on_an_offset():
    k = fleet(40, seed=1)
    rng = np.random.default_rng(2)
    for i in range(40):  # each one damaged on its own component
        k[i, rng.integers(0, 6)] += rng.uniform(0.05, 0.3)
    assert not check_fleet(first_inspections(k), NOMINAL, FleetCheckSettings())["offset"]


def test_too_few_usable_first_inspections_are_not_checked_and_bad_settings_are_refused():
    shift = np.zeros(8)
    shift[0] = 0.05
    few = check_fleet(first_inspections(fleet(6, shift), ood=2), NOMINAL, FleetCheckSettings())
    assert not few["checked"] and few["n_actuators"] == 4 and not few["offset"]
    with pytest.raises(ValueError, match="fleet_check.action must be 'refuse' or 'warn', got 'ignore'"):
        FleetCheckSettings(action="ignore")
    with pytest.raises(ValueError, match=r"fleet_check.agree must be in \(0.5, 1\]"):
        FleetCheckSettings(agree=0.4)
    with pytest.raises(ValueError, match="fleet_check.min_actuators must be an integer >= 2"):
        FleetCheckSettings(min_actuators=1)
