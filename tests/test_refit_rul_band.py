"""scripts/refit_pipeline_classifiers.py --rul-band: an exported pipeline's physics RUL band calibrated again under
a damage law with the wear-rate scale, as phm-evaluate calibrates it, so that it holds the law's own spread."""

from __future__ import annotations

import pytest
import torch
from script_module import script_module
from test_tracking import NOMINAL, damage_config, make_pipeline

RUL = {"n_samples": 100, "refine_iterations": 6, "band": "rate", "delta_bracket": 0.05}


def _near_nominal(n: int = 12) -> torch.Tensor:
    g = torch.Generator().manual_seed(1)
    k = torch.tensor(NOMINAL, dtype=torch.float64).repeat(n, 1)
    k[:, :6] += 0.05 + 0.1 * torch.rand(n, 6, generator=g, dtype=torch.float64)
    return k


def test_the_band_holds_the_wear_rate_scale_it_did_not_before():
    script = script_module("refit_pipeline_classifiers")
    pipe = make_pipeline()  # exported without a band: a point at the median
    law = {"_target_": "phm_torch.prognostics.DamageModel", **damage_config()}  # rate_scale_sigma 0.35
    report = script.physics_band(pipe, law, NOMINAL, RUL, _near_nominal(), seed=0)
    before, after = report["before"], report["after"]
    # (a quarter of these vectors never fail within the horizon: in the band either way)
    assert before["holds_monte_carlo"] < 0.3 and after["holds_monte_carlo"] > 0.85
    # the 5-95 % actuators wear 0.56-1.78 times the median rate: the clock factors hold at least that
    assert after["rate_scales"][0] > 1.7 and after["rate_scales"][2] < 0.6
    assert pipe.rate_scales.tolist() == pytest.approx(after["rate_scales"])
    # without the scale the same calibration gives a band of eps alone, far narrower
    narrow = script.physics_band(make_pipeline(), {**law, "rate_scale_sigma": 0.0}, NOMINAL, RUL, _near_nominal(), 0)
    assert narrow["after"]["rate_scales"][0] < 1.2


def test_a_damage_law_that_is_not_the_pipelines_is_refused():
    script = script_module("refit_pipeline_classifiers")
    law = {"_target_": "phm_torch.prognostics.DamageModel", **damage_config()}
    law["rate"] = (torch.tensor(law["rate"]) * 2).tolist()
    pipe = make_pipeline()
    with pytest.raises(ValueError, match="propagators are not the pipeline's"):
        script.physics_band(pipe, law, NOMINAL, RUL, _near_nominal(), seed=0)
    assert float(pipe.rate_scales.sub(1).abs().max()) == 0.0  # nothing changed
