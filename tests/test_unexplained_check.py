"""The ``unexplained`` check (phm_torch/online/unexplained_check.py): a near-nominal answer's gappy residual against
the model's floor and the record's white noise; its floor from the pipeline's own nominal record."""

from __future__ import annotations

import math
from pathlib import Path
from types import SimpleNamespace

import pytest
import torch

from phm_torch.online.diagnosis import contract_for
from phm_torch.online.export import read_metadata
from phm_torch.online.loaded import load_pipeline
from phm_torch.online.unexplained_check import FLOOR_LEVEL, residual_floor, unexplained_ratio

PIPELINE = Path(__file__).resolve().parents[1] / "pretrained" / "online_surrogates_best.pt"


def test_ratio_is_one_when_floor_and_white_noise_explain_the_residual():
    floor, noise, rms = 0.03, 0.02, 0.8
    explained = math.sqrt(floor**2 + (noise * rms) ** 2)
    assert unexplained_ratio(explained, noise, rms, floor) == pytest.approx(1.0)
    assert unexplained_ratio(3.0 * explained, noise, rms, floor) == pytest.approx(3.0)
    assert unexplained_ratio(floor, math.nan, rms, floor) == pytest.approx(1.0)  # no noise estimate: the floor alone


def test_floor_is_the_nominal_residual_with_a_least_level_in_quadrature():
    nominal = torch.full((100,), 2.0)  # RMS 2 A

    def run(x: torch.Tensor) -> SimpleNamespace:
        assert x.shape == (1, 100)
        return SimpleNamespace(residual=torch.tensor([0.03]))

    least = FLOOR_LEVEL * 2.0
    assert residual_floor(run, nominal) == pytest.approx(math.sqrt(0.03**2 + least**2))
    assert residual_floor(run, None) is None
    assert residual_floor(run, torch.full((100,), math.nan)) is None


@pytest.mark.torchscript
def test_contract_of_the_pretrained_pipeline_takes_its_nominal_residual_as_floor():
    model = load_pipeline(PIPELINE)
    contract = contract_for(model, read_metadata(PIPELINE), None)
    with torch.no_grad():
        own = float(model.run(model.nominal_record.reshape(1, -1)).residual[0])
    assert 0.0 < own <= contract.residual_floor < 1.01 * own  # the model's truncation floor dominates here
    # the nominal record with 2 % white noise is explained; with a 40 % 400 Hz hum it is not
    nominal = model.nominal_record.double()
    rms = float(nominal.pow(2).mean().sqrt())
    t = torch.arange(nominal.numel(), dtype=torch.float64) / float(model.sample_rate)
    gen = torch.Generator().manual_seed(0)
    for added, expected in (
        (0.02 * rms * torch.randn(nominal.numel(), generator=gen, dtype=torch.float64), False),
        (0.4 * rms * math.sqrt(2.0) * torch.sin(2 * math.pi * 400.0 * t), True),
    ):
        x = (nominal + added).to(model.dtype)
        with torch.no_grad():
            out = model.run(x.reshape(1, -1))
        reasons = contract.current_reasons(
            model, x.double(), float(out.noise[0]), out.k_hat[0], residual=float(out.residual[0])
        )
        assert ("unexplained" in reasons) is expected, reasons


@pytest.mark.torchscript
def test_a_pipeline_calibrates_its_own_threshold_never_below_the_default():
    from phm_torch.online.from_torchscript import pipeline_from_torchscript
    from phm_torch.online.input_contract import InputContract
    from phm_torch.online.unexplained_check import CALIBRATION_MARGIN, UNEXPLAINED_RATIO, calibrate_ratio

    pipeline, _ = pipeline_from_torchscript(PIPELINE)
    nominal = pipeline.nominal_record.double()
    rms = float(nominal.pow(2).mean().sqrt())
    gen = torch.Generator().manual_seed(1)
    noisy = nominal + 0.01 * rms * torch.randn(4, nominal.numel(), generator=gen, dtype=torch.float64)
    t = torch.arange(nominal.numel(), dtype=torch.float64) / float(pipeline.sample_rate)
    hummed = noisy + 0.3 * rms * math.sqrt(2.0) * torch.sin(2 * math.pi * 400.0 * t)
    with torch.no_grad():
        k_noisy, k_hummed = pipeline(noisy.float())[0], pipeline(hummed.float())[0]
    assert calibrate_ratio(pipeline, noisy.float(), k_noisy) == UNEXPLAINED_RATIO  # explained: the default
    loose = calibrate_ratio(pipeline, hummed.float(), k_hummed)  # held-out records the modes cannot explain
    assert loose is not None and loose > CALIBRATION_MARGIN * UNEXPLAINED_RATIO
    assert InputContract.of(pipeline, {"unexplained_ratio_max": loose}, None).unexplained_ratio == loose
    assert InputContract.of(pipeline, {"unexplained_ratio_max": 1.5}, None).unexplained_ratio == UNEXPLAINED_RATIO
    assert calibrate_ratio(pipeline, noisy[:0].float(), k_noisy[:0]) is None
