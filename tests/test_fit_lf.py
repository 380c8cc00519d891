"""LF shape fit (phm_torch/lf_fit.py) and its app phm-fit-lf: recovery of known coefficients, the decision
rule, config validation, a tiny end-to-end run."""

from __future__ import annotations

import dataclasses
import json

import pytest
import torch

from phm_torch import lf_fit
from phm_torch.apps.fit_lf import fit_lf
from phm_torch.command import Sine
from phm_torch.params import ActuatorParams, LFShape, load_actuator

TRUTH = LFShape(emf_short_gain=0.8, resistance_short_gain=1.25, inductance_short_exponent=2.5, commutation_width=0.15)
# A fast sine: the motor turns through several commutations within a short record.
COMMAND = Sine(amplitude=5e-3, frequency=10.0, duration=0.03)


def _faults(rows: list[dict[int, float]], nominal: tuple[float, ...]) -> torch.Tensor:
    out = torch.tensor([nominal] * len(rows), dtype=torch.float64)
    for i, row in enumerate(rows):
        for j, v in row.items():
            out[i, j] = v
    return out


@pytest.fixture(scope="module")
def synthetic(params):
    """Fit on LF targets simulated with the known ``TRUTH``; held out: ``importance`` also from TRUTH,
    ``uniform`` from the physical coefficients (so the fit improves one held-out set and worsens the other)."""
    nominal = params.nominal_faults
    sets = {
        "design": _faults([{}, {2: 0.3}, {3: 0.6}, {4: 0.8, 5: 0.5}, {2: 0.5, 3: 0.2}, {5: 0.8, 6: 0.3}], nominal),
        "importance": _faults([{2: 0.4}, {4: 0.5, 5: 0.3}], nominal),
        "uniform": _faults([{3: 0.4}, {2: 0.7, 5: 0.5}], nominal),
    }

    def run(faults: torch.Tensor, shape: LFShape) -> torch.Tensor:
        shapes = lf_fit.as_vector(shape).expand(faults.shape[0], -1)
        return lf_fit.simulate(params, "lf", faults, COMMAND, COMMAND.duration, shapes)

    refs = {
        "design": run(sets["design"], TRUTH),
        "importance": run(sets["importance"], TRUTH),
        "uniform": run(sets["uniform"], LFShape()),
    }
    settings = lf_fit.LFFitSettings(n_design=6, n_importance=2, n_uniform=2, max_iter=8, seed=0)
    return lf_fit.fit_and_validate(params, COMMAND, COMMAND.duration, sets, refs, settings)


def test_fit_recovers_known_coefficients(synthetic):
    fitted = dataclasses.asdict(synthetic.fit.shape)
    for name, truth in dataclasses.asdict(TRUTH).items():
        assert fitted[name] == pytest.approx(truth, abs=0.02), name
    # the design discrepancy falls from that of the physical values to (almost) nothing
    design = synthetic.summary["design"]
    assert design["fitted"]["current"]["median"] < 0.05 * design["physical"]["current"]["median"]


def test_fit_worsening_one_held_out_set_keeps_physical_values(synthetic):
    imp, uni = synthetic.summary["importance"], synthetic.summary["uniform"]
    assert imp["fitted"]["current"]["median"] < 0.5 * imp["physical"]["current"]["median"]  # better here
    assert uni["fitted"]["current"]["median"] > uni["physical"]["current"]["median"]  # worse there
    assert synthetic.decision.keep == "physical"
    assert synthetic.shape == LFShape()
    assert any(r.startswith("uniform current") and "worsens" in r for r in synthetic.decision.reasons)
    assert not any(r.startswith("importance") for r in synthetic.decision.reasons)


def _summary(cur_med: float, cur_max: float, pos_med: float = 0.01, pos_max: float = 0.02) -> dict:
    return {"current": {"median": cur_med, "max": cur_max}, "position": {"median": pos_med, "max": pos_max}}


def test_decide_rule():
    before = {"importance": _summary(0.02, 0.10), "uniform": _summary(0.09, 0.18)}
    better = {"importance": _summary(0.015, 0.09), "uniform": _summary(0.08, 0.18)}
    assert lf_fit.decide(before, better).keep == "fitted"
    # the max worsens on one set (the case): physical values, and the reason says which number
    worse_max = {"importance": _summary(0.015, 0.134), "uniform": _summary(0.08, 0.17)}
    d = lf_fit.decide(before, worse_max)
    assert d.keep == "physical" and d.reasons == ["importance current max NRMSE worsens 10.00 -> 13.40 %"]
    # ... unless a tolerance allows it
    assert lf_fit.decide(before, worse_max, max_worsening=0.5).keep == "fitted"
    # too small a gain on one set
    small = {"importance": _summary(0.0199, 0.10), "uniform": _summary(0.08, 0.18)}
    d = lf_fit.decide(before, small, min_gain=0.02)
    assert d.keep == "physical" and "importance median current NRMSE falls by 0.5 %" in d.reasons[0]
    assert lf_fit.decide(before, small, min_gain=0.0).keep == "fitted"


def _cfg(compose, tmp_path, *overrides: str):
    return compose(
        "fit_lf",
        [
            "command=sine",
            "command.frequency=10",
            "command.duration=0.01",
            "fit.n_design=3",
            "fit.n_importance=2",
            "fit.n_uniform=2",
            "fit.max_iter=1",
            f"out={tmp_path / 'act' / 'ema_lf.yaml'}",
            *overrides,
        ],
    )


@pytest.mark.parametrize(
    "override, message",
    [
        ("+fit.bogus=1", "bogus"),
        ("fit.n_design=-4", "fit.n_design must be an integer >= 2, got -4"),
        ("fit.n_uniform=0", "fit.n_uniform"),
        ("+fit.min_gain=1.5", "fit.min_gain"),
        ("+fit.duration=0.00015", "fit.duration"),
        ("+fit.outlier_factor=0.5", "fit.outlier_factor"),
        ("+fit.bounds={commutation_width: [0.1, 0.2]}", "fit.bounds.commutation_width"),
        ("+fit.bounds={turns: [0, 1]}", "turns"),
        ("out=fit.csv", "out must end in .yaml"),
    ],
)
def test_bad_config_names_the_field(compose, tmp_path, override, message):
    with pytest.raises(ValueError, match=message.replace("[", r"\[").replace(".", r"\.")):
        fit_lf(_cfg(compose, tmp_path, override))
    assert not (tmp_path / "act").exists()  # validated before anything is written


def test_app_tiny_run_writes_usable_actuator_yaml(compose, tmp_path, monkeypatch, caplog):
    import phm_torch.apps.fit_lf as app

    monkeypatch.setattr(app, "LONG_FIT_PERIODS", 50)  # this tiny run's 0.01 s at 10 kHz are 100 periods
    with caplog.at_level("WARNING", logger=app.__name__):
        metrics, objects = fit_lf(_cfg(compose, tmp_path))
    assert "100 control periods per simulated vector" in caplog.text and "fit.duration=<s>" in caplog.text
    path = objects["yaml"]
    written = load_actuator(str(path))
    assert isinstance(written, ActuatorParams)
    reference = load_actuator()
    assert dataclasses.replace(written, lf_shape=reference.lf_shape) == reference  # only lf_shape replaced
    assert dataclasses.asdict(written.lf_shape) == pytest.approx(metrics["lf_shape"])
    report = json.loads(objects["report"].read_text())
    assert report["provenance"]["actuator"]["name"] == "ema_reference"
    assert report["provenance"]["command"]["params"]["frequency"] == 10.0
    header = path.read_text().split("\n", 4)[3]
    assert json.loads(header.split(": ", 1)[1]) == report["provenance"]
    # the decision follows the rule on the reported numbers, and the coefficients kept are the right ones
    held = {n: {k: report["nrmse"][n][k] for k in ("physical", "fitted")} for n in lf_fit.HELD_OUT}
    decision = lf_fit.decide({n: held[n]["physical"] for n in held}, {n: held[n]["fitted"] for n in held})
    assert report["kept"] == decision.keep and report["reasons"] == decision.reasons
    assert report["lf_shape"] == report[decision.keep]
    assert objects["plot"].stat().st_size > 1000
