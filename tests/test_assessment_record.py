"""Which phi_a an artefact's labels came from: run-only settings aside, two configs label alike or not."""

from __future__ import annotations

from phm_torch.assessment_record import labelling, same_labels

SWEEP = {"_target_": "phm_torch.assessment.SineSweep", "frequencies": "auto", "compile": False, "group_size": 4}
DERIVED = {
    "_target_": "phm_torch.assessment.AssessmentFunction",
    "sweep": SWEEP,
    "requirements": {"gain_margin_db": 6.0},
}


def test_run_only_settings_do_not_change_the_labels():
    compiled = {**DERIVED, "sweep": {**SWEEP, "compile": True, "group_size": 8}}
    assert labelling(compiled) == labelling(DERIVED) and "compile" not in labelling(DERIVED)["sweep"]
    assert same_labels(DERIVED, compiled) is True


def test_another_grid_or_requirement_labels_differently_and_unknown_is_none():
    hand_tuned = {**DERIVED, "sweep": {**SWEEP, "frequencies": [12.0, 20.0, 40.0, 80.0, 160.0]}}
    stricter = {**DERIVED, "requirements": {"gain_margin_db": 8.0}}
    assert same_labels(DERIVED, hand_tuned) is False and same_labels(DERIVED, stricter) is False
    assert same_labels(None, DERIVED) is None and labelling(None) is None


def test_a_sweep_setting_left_out_is_its_code_default():
    """A store made before the shipped config set settling records no max_extensions/refine: it labels as one that
    records 0 (SineSweep's defaults, which SWEEP_DEFAULTS must follow), and not as the settled one."""
    import dataclasses

    from phm_torch.assessment import SineSweep
    from phm_torch.assessment_record import SWEEP_DEFAULTS

    code = {f.name: f.default for f in dataclasses.fields(SineSweep) if f.name in SWEEP_DEFAULTS}
    assert code == SWEEP_DEFAULTS
    explicit = {**DERIVED, "sweep": {**SWEEP, "max_extensions": 0, "refine": 0}}
    settled = {**DERIVED, "sweep": {**SWEEP, "max_extensions": 2, "refine": 1}}
    assert same_labels(DERIVED, explicit) is True and same_labels(DERIVED, settled) is False
    # a store labelled before rotor positions existed read the loop at rest at 0 only
    assert same_labels(DERIVED, {**DERIVED, "sweep": {**SWEEP, "rotor_positions": 1}}) is True
    assert same_labels(DERIVED, {**DERIVED, "sweep": {**SWEEP, "rotor_positions": 3}}) is False
