"""Bad input is refused with an error naming the field and the value; nothing is clamped silently."""

from __future__ import annotations

import math

import pytest
import torch

from phm_torch.command import Chirp
from phm_torch.params import load_actuator
from phm_torch.simulator import EMASimulator

P = load_actuator()
NOM = list(P.nominal_faults)


@pytest.mark.parametrize(
    "faults,match",
    [
        ([1.2] + NOM[1:], r"faults\[0\]\[0\] \(dry_friction\) = 1\.2"),
        (NOM[:7] + [-0.1], r"faults\[0\]\[7\] \(gain_drift\) = -0\.1"),
        (NOM[:3] + [math.nan] + NOM[4:], r"faults\[0\]\[3\] \(short_b\) is not finite"),
        (NOM[:7], r"shape \(8,\) or \(B, 8\), got \(1, 7\)"),
        ([[NOM]], r"shape"),
    ],
)
def test_bad_fault_vectors(faults, match):
    with pytest.raises(ValueError, match=match):
        EMASimulator(P, "lf").run(torch.tensor(faults), Chirp(), 0.01)


@pytest.mark.parametrize(
    "field,value", [("phase_resistance", -0.7), ("motor_inertia", 0.0), ("gear_ratio", math.nan), ("backlash", -1e-6)]
)
def test_non_positive_physical_parameter(field, value):
    with pytest.raises(ValueError, match=f"actuator.{field}"):
        load_actuator(**{field: value})


def test_unknown_actuator_parameter():
    with pytest.raises(ValueError, match="unknown parameter.*'bogus'"):
        load_actuator(bogus=1.0)


def test_unknown_fidelity_and_scales():
    with pytest.raises(ValueError, match="fidelity must be one of"):
        EMASimulator(P, "mf")
    with pytest.raises(ValueError, match="scales: unknown parameter 'nope'"):
        EMASimulator(P, "lf").run(torch.tensor([NOM]), Chirp(), 0.01, scales={"nope": torch.tensor(1.0)})
    with pytest.raises(ValueError, match="scales.motor_inertia must be finite and > 0"):
        EMASimulator(P, "lf").run(torch.tensor([NOM]), Chirp(), 0.01, scales={"motor_inertia": torch.tensor(-1.0)})


def test_unknown_effect_and_parameter():
    with pytest.raises(ValueError, match="unknown effect 'warp_drive'"):
        EMASimulator(P, "lf", effects={"warp_drive": {}})
    with pytest.raises(ValueError, match=r"effects.cogging_torque: unknown parameter\(s\) \['amp'\]"):
        EMASimulator(P, "lf", effects={"cogging_torque": {"amp": 1.0}})
    with pytest.raises(ValueError, match="effects.cogging_torque.amplitude must be >= 0"):
        EMASimulator(P, "lf", effects={"cogging_torque": {"amplitude": -1.0}})


def test_bad_command():
    sim = EMASimulator(P, "lf")
    with pytest.raises(ValueError, match="command has 5 samples"):
        sim.run(torch.tensor([NOM]), torch.zeros(5), 0.01)
    with pytest.raises(ValueError, match="command.amplitude must be > 0"):
        Chirp(amplitude=-1.0)
    with pytest.raises(ValueError, match="channels: unknown"):
        sim.run(torch.tensor([NOM]), Chirp(), 0.01, channels=["voltage"])
