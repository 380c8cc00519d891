"""The tracking's information limit (phm_torch.tracking.information_limit): the tracker fed the true k."""

from __future__ import annotations

import pytest
import torch
from test_tracking import damage_config, make_pipeline, truth_path

from phm_torch.faults import FAULT_NAMES
from phm_torch.tracking import DamageLaw, ParticleRUL, Tracker, TrackerSettings
from phm_torch.tracking.information_limit import fused_readings, information_limit, track_truth

EVERY = 200.0


@pytest.fixture(scope="module")
def setup():
    pipeline = make_pipeline()
    return pipeline, DamageLaw.from_config(damage_config(), pipeline, "test")


def fresh_tracker(pipeline, law, **kw) -> Tracker:
    settings = TrackerSettings(**{"n_particles": 256, "rul_particles": 64, **kw})
    return Tracker(law, ParticleRUL(pipeline, law, settings.max_rate_scale, settings.bisections), settings)


def limit_of(pipeline, law, truth: dict, *args, **kw) -> dict:
    """information_limit of a fresh tracker's track_truth(truth, *args, **kw)."""
    return information_limit(track_truth(fresh_tracker(pipeline, law), truth, *args, **kw), truth)


def life_truth(pipeline, law) -> dict:
    """Noise-free histories at rate scales 0.7-1.4 from small damages, inspected every 200 h until two inspections
    after the pipeline's classifier turns faulty; the end of life is where it turns faulty on a 1 h grid."""
    rul = ParticleRUL(pipeline, law)
    fine = torch.arange(0.0, 12000.0, 1.0, dtype=torch.float64)
    actuators = {}
    for a, (s, start) in enumerate([(0.7, 0.03), (1.0, 0.02), (1.4, 0.02), (1.0, 0.04), (0.85, 0.03), (1.2, 0.03)]):
        dk = torch.tensor([start] * 6 + [0.5, 0.5], dtype=torch.float64) - law.nominal
        path = law.nominal + law.propagate(dk.expand(len(fine), -1), s * fine)
        eol = float(fine[int((rul.score(path) <= 0).double().argmax())])
        k = truth_path(law, (dk + law.nominal).tolist(), s, 60, EVERY)
        n = int(eol // EVERY) + 3
        actuators[f"A{a}"] = {
            "rate_scale": s,
            "eol_hours": eol,
            "inspections": [
                {"hours": j * EVERY, "k_true": k[j].tolist(), "healthy": j * EVERY < eol, "rul_true": eol - j * EVERY}
                for j in range(n)
            ],
        }
    return {"every_hours": EVERY, "actuators": actuators}


def test_the_classifier_on_the_true_k_flags_the_end_of_life_it_defines_and_the_tracker_follows(setup):
    pipeline, law = setup
    truth = life_truth(pipeline, law)
    found = limit_of(pipeline, law, truth, error_std=1e-4)
    assert found["n_actuators"] == 6
    # the first inspection at or after the end of life the classifier itself defines
    assert found["classifier_on_true_k"]["eol_flagged_within_one_inspection"] == 1.0
    assert 0.0 <= found["classifier_on_true_k"]["eol_detection_delay"] < EVERY
    tracking = found["tracking"]
    # exact readings of a noise-free law: the s of each actuator learnt early, the true RUL covered
    assert tracking["eol_flagged_within_one_inspection"] == 1.0
    assert tracking["positive_p50_when_faulty"] == 0
    assert tracking["coverage_5_95"] >= 0.85
    assert tracking["alpha_lambda"] == 1.0
    assert tracking["prognostic_horizon"] >= 0.85


def test_the_limit_falls_as_the_measurement_worsens(setup):
    pipeline, law = setup
    truth = life_truth(pipeline, law)
    exact = limit_of(pipeline, law, truth, error_std=1e-4)["tracking"]
    poor = limit_of(pipeline, law, truth, error_std=0.03)["tracking"]
    # a 3 % error on every component hides the rate scale for most of the life
    assert poor["prognostic_horizon"] < exact["prognostic_horizon"] - 0.3
    assert poor["p50_within_alpha_second_half"] < exact["p50_within_alpha_second_half"] - 0.3


def test_the_track_has_phm_tracks_layout_and_a_censored_bound_is_null(setup):
    pipeline, law = setup
    truth = life_truth(pipeline, law)
    track = track_truth(fresh_tracker(pipeline, law, verdict="posterior"), truth, error_std=1e-3, seed=3)
    first = track["actuators"]["A0"]["inspections"][0]
    assert set(first) >= {"hours", "k_hat", "rul_hours", "rul_censored", "healthy", "out_of_distribution"}
    assert first["rul_hours"]["p95"] is None or first["rul_hours"]["p95"] < law.horizon_hours
    assert first["rul_censored"] == any(v is None for v in first["rul_hours"].values())
    k_true = torch.tensor(truth["actuators"]["A0"]["inspections"][0]["k_true"])
    assert torch.allclose(torch.tensor(first["k_hat"]), k_true, atol=6e-3)  # within 6 std of 1e-3
    again = track_truth(fresh_tracker(pipeline, law, verdict="posterior"), truth, error_std=1e-3, seed=3)
    assert again == track  # seeded


@pytest.mark.parametrize(
    ("change", "message"),
    [
        ({"error_std": 0.0}, "error_std must be a finite number > 0"),
        ({"error_std": float("nan")}, "error_std must be a finite number > 0"),
        ({"k_true": [0.1] * 7}, "actuator 'A0' inspection 1: k_true must be 8 finite values"),
        ({"hours": 0.0}, "actuator 'A0' inspection 1: hours 0.0 not increasing"),
        ({"truth": {}}, "non-empty 'actuators'"),
    ],
)
def test_bad_input_names_the_field_and_the_value(setup, change, message):
    pipeline, law = setup
    truth = life_truth(pipeline, law)
    row = truth["actuators"]["A0"]["inspections"][1]
    if "k_true" in change:
        row["k_true"] = change["k_true"]
    if "hours" in change:
        row["hours"] = change["hours"]
    with pytest.raises(ValueError, match=message):
        track_truth(fresh_tracker(pipeline, law), change.get("truth", truth), change.get("error_std", 1e-4))


def test_a_used_tracker_is_refused(setup):
    pipeline, law = setup
    truth = life_truth(pipeline, law)
    tracker = fresh_tracker(pipeline, law)
    track_truth(tracker, truth)
    with pytest.raises(ValueError, match="give it a fresh one"):
        track_truth(tracker, truth)


def run_track_of(truth: dict, width: float, near_nominal: dict | None = None) -> dict:
    """A phm-track track.json whose readings are the true k off by +-width / 2 (alternating) with a 90 % interval of
    +-width around them (and, for A0's first inspection, a near-nominal reading ``near_nominal``)."""
    names = list(FAULT_NAMES)
    actuators = {}
    for a, history in truth["actuators"].items():
        rows = []
        for j, row in enumerate(history["inspections"]):
            k = {n: v + (-1) ** j * width / 2 for n, v in zip(names, row["k_true"])}
            rows.append({"k_hat": k, "k_interval": {n: [v - width, v + width] for n, v in k.items()}})
        actuators[a] = {"inspections": rows}
    if near_nominal is not None:
        first = actuators["A0"]["inspections"][0]
        first["k_hat_near_nominal"] = near_nominal
        first["k_hat_near_nominal_interval"] = {n: [v - 1e-3, v + 1e-3] for n, v in near_nominal.items()}
    return {"actuators": actuators}


def test_a_component_read_as_a_run_fused_it_costs_the_horizon_its_error_does(setup):
    pipeline, law = setup
    truth = life_truth(pipeline, law)
    near = dict(zip(FAULT_NAMES, [0.5] * 8))
    readings = fused_readings(run_track_of(truth, 0.08, near))
    # the near-nominal reading first, its scale the interval's half-width over the normal's 95 % quantile
    assert readings["A0"][0][0].tolist() == [0.5] * 8
    assert readings["A0"][0][1].tolist() == pytest.approx([1e-3 / 1.6448536269514722] * 8)
    assert readings["A0"][1][1].tolist() == pytest.approx([0.08 / 1.6448536269514722] * 8)
    readings = fused_readings(run_track_of(truth, 0.02))
    exact = limit_of(pipeline, law, truth, 1e-4)
    one = limit_of(pipeline, law, truth, 1e-4, readings=readings, components=(0,))
    every = limit_of(pipeline, law, truth, 1e-4, readings=readings, components=tuple(range(8)))
    assert one["components_as_read"] == ["dry_friction"]
    # one component 0.01 off at every inspection: the other seven still give s; all eight off: the horizon is lost
    assert one["tracking"]["prognostic_horizon"] > exact["tracking"]["prognostic_horizon"] - 0.05
    assert every["tracking"]["prognostic_horizon"] < exact["tracking"]["prognostic_horizon"] - 0.5
    with pytest.raises(ValueError, match="needs the readings of a phm-track run"):
        track_truth(fresh_tracker(pipeline, law), truth, components=(0,))
    with pytest.raises(ValueError, match=r"components must be in \[0, 8\), got \[8\]"):
        track_truth(fresh_tracker(pipeline, law), truth, readings=readings, components=(8,))
