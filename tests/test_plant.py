"""The frozen Plant: faults, scales and effects return new plants and never change what they were given."""

from __future__ import annotations

import dataclasses
import math

import pytest
import torch

from phm_torch.effects import EFFECTS, Effect, build_effects
from phm_torch.faults import apply_faults
from phm_torch.params import load_actuator
from phm_torch.plant import LF_FIELDS, TENSOR_FIELDS, Plant, build_plant
from phm_torch.simulator import EMASimulator

P = load_actuator()
PER_PHASE = ("short", "resistance", "inductance", "emf")


def snapshot(plant: Plant) -> dict[str, torch.Tensor]:
    return {k: v.clone() for k, v in plant.to_dict().items()}


def unchanged(plant: Plant, before: dict[str, torch.Tensor]) -> bool:
    return all(torch.equal(v, before[k]) for k, v in plant.to_dict().items())


def test_plant_is_frozen_with_every_datasheet_field_typed():
    plant = Plant.nominal(P, 4, torch.float64, "cpu")
    with pytest.raises(dataclasses.FrozenInstanceError):
        plant.backlash = plant.backlash * 2  # type: ignore[misc]
    names = set(plant.to_dict())
    assert names == {*TENSOR_FIELDS, *LF_FIELDS, *PER_PHASE, "eccentricity", "ecc_phase"}
    for name, value in plant.to_dict().items():
        assert value.shape == ((4, 3) if name in PER_PHASE else (4,)), name
    assert plant.batch == 4 and plant.pole_pairs_f == float(P.pole_pairs)
    # healthy per-phase values: the datasheet's, no shorted turn, no eccentricity
    assert torch.equal(plant.resistance, torch.full((4, 3), P.phase_resistance, dtype=torch.float64))
    assert not plant.short.any() and not plant.eccentricity.any()


def test_apply_faults_returns_a_new_plant_with_the_fault_mapping():
    k = torch.tensor([[0.5, 0.2, 0.4, 0.0, 0.99, 0.6, 0.75, 0.25]], dtype=torch.float64)
    nominal = Plant.nominal(P, 1, torch.float64, "cpu")
    before = snapshot(nominal)
    plant = apply_faults(nominal, k, P.short_circuit_max)
    assert plant is not nominal and unchanged(nominal, before)
    assert plant.coulomb_friction.item() == pytest.approx(2.0 * P.coulomb_friction)  # 1 + 2 k1
    assert plant.backlash.item() == pytest.approx(P.backlash * (1 + 99 * 0.2))
    s = torch.tensor([0.4, 0.0, P.short_circuit_max], dtype=torch.float64)  # k5 clamped
    assert torch.allclose(plant.short[0], s)
    assert torch.allclose(plant.resistance[0], P.phase_resistance * (1 - s))
    assert torch.allclose(plant.inductance[0], P.phase_inductance * (1 - s) ** 2)
    assert torch.allclose(plant.emf[0], P.back_emf_constant * (1 - s))
    assert plant.eccentricity.item() == pytest.approx(0.3) and plant.ecc_phase.item() == pytest.approx(0.5 * math.pi)
    assert plant.position_gain.item() == pytest.approx(0.75 * P.position_gain)
    # build_plant = nominal -> scales -> faults, the scaled value carried into the per-phase tensors
    scaled = build_plant(P, k, {"phase_resistance": torch.tensor(2.0, dtype=torch.float64)})
    assert torch.allclose(scaled.resistance, 2.0 * plant.resistance)


def test_static_effects_leave_the_given_plant_unchanged():
    plant = build_plant(P, torch.tensor([P.nominal_faults], dtype=torch.float64))
    before = snapshot(plant)
    static = [name for name, cls in EFFECTS.items() if cls.modify_plant is not Effect.modify_plant]
    assert {"winding_temperature", "transmission_compliance", "position_sensor_lag"} <= set(static)
    for eff in build_effects({name: {} for name in static}):
        out = eff.modify_plant(plant)
        assert isinstance(out, Plant) and out is not plant, eff.name
        assert any(not torch.equal(v, before[k]) for k, v in out.to_dict().items()), eff.name  # it did act
        assert unchanged(plant, before), eff.name


def test_simulator_copies_the_callers_effects():
    effects = build_effects(
        {"viscous_friction": {"coefficient": torch.tensor(2e-4, dtype=torch.float32)}, "winding_temperature": {}}
    )
    given = [e.values for e in effects]
    dtypes = [{k: v.dtype for k, v in e.values.items()} for e in effects]
    sim = EMASimulator(P, "lf", effects=effects)
    for e, values, dt in zip(effects, given, dtypes, strict=True):
        assert e.values is values and {k: v.dtype for k, v in e.values.items()} == dt  # left as given
    assert all(v.dtype == torch.float64 for e in sim.effects for v in e.values.values())
    k = torch.tensor([P.nominal_faults], dtype=torch.float64)
    same = EMASimulator(
        P,
        "lf",
        effects={
            "viscous_friction": {"coefficient": float(torch.tensor(2e-4, dtype=torch.float32))},
            "winding_temperature": {},
        },
    )
    assert torch.equal(
        sim.run(k, lambda t: 0.01 * torch.sin(200 * t), 0.002)["current"],
        same.run(k, lambda t: 0.01 * torch.sin(200 * t), 0.002)["current"],
    )


def test_an_effect_that_mutates_instead_of_returning_is_named():
    class OldStyle(Effect):
        name = "old_style"

        def modify_plant(self, plant):  # the pre-frozen hook: returns None
            return None

    with pytest.raises(TypeError, match="old_style.modify_plant must return the new Plant"):
        EMASimulator(P, "lf", effects=[OldStyle()]).init(torch.tensor([P.nominal_faults]))
