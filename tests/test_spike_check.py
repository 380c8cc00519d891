"""The input contract's ``spikes`` check: a step threshold phm-evaluate calibrates per pipeline (never below
SPIKE_STEP), so that a coarsely sampled actuator's own steps are not spikes while a single-sample spike still is."""

from __future__ import annotations

import math
from types import SimpleNamespace

import pytest
import torch
from contract_model import contract_model

from phm_torch.online.fault_count import no_large_fault
from phm_torch.online.input_contract import InputContract
from phm_torch.online.spike_check import SPIKE_MARGIN, SPIKE_STEP, calibrate_spike_step, has_spikes, largest_step


def coarse(n: int, cycles_per_sample: float) -> torch.Tensor:
    """A smooth chirp over n samples ending at ``cycles_per_sample``: a current sampled only a few times a cycle
    at the end of its test command (a coarse acquisition)."""
    t = torch.arange(n, dtype=torch.float64) / n
    return torch.sin(math.pi * cycles_per_sample * n * t * t)


N = 1000
NOMINAL = coarse(N, 0.15)


def model() -> SimpleNamespace:
    return contract_model(NOMINAL)


def test_a_coarsely_sampled_record_steps_by_itself_and_the_calibrated_step_lets_it_through():
    m = model()
    scale = float(NOMINAL.pow(2).mean().sqrt())
    own = float(largest_step(NOMINAL)) / scale
    assert own > SPIKE_STEP  # its own steps above the reference's threshold: refused as spikes before
    assert has_spikes(NOMINAL, 0.0, scale)
    near = torch.tensor([0.0] * 6 + [0.5, 0.5], dtype=torch.float64)
    heavy = near.clone()
    heavy[1] = 0.9
    wild = NOMINAL.clone()
    wild[300] += 5 * scale  # a large fault's record is not compared: it does not set the threshold
    signals, k_hat = torch.stack([NOMINAL, 0.9 * NOMINAL, wild]), torch.stack([near, near, heavy])
    assert no_large_fault(m, k_hat).tolist() == [True, True, False]
    step = calibrate_spike_step(m, signals, k_hat)
    assert step == pytest.approx(SPIKE_MARGIN * own)
    assert not has_spikes(NOMINAL, 0.0, scale, step)
    spiked = NOMINAL.clone()
    spiked[500] += 2 * step * scale  # a single-sample spike twice the calibrated step
    assert has_spikes(spiked, 0.0, scale, step)
    # the contract reads it from the pipeline's metadata, never below SPIKE_STEP
    strict, calibrated = InputContract.of(m, {}, None), InputContract.of(m, {"spike_step_max": step}, None)
    assert strict.spike_step == SPIKE_STEP and calibrated.spike_step == step
    assert "spikes" in strict.current_reasons(m, NOMINAL, 0.0, near)
    assert "spikes" not in calibrated.current_reasons(m, NOMINAL, 0.0, near)
    assert "spikes" in calibrated.current_reasons(m, spiked, 0.0, near)
    assert InputContract.of(m, {"spike_step_max": 0.1}, None).spike_step == SPIKE_STEP
    # a record drawing 1.4x the nominal current steps 1.4x as much: measured against its own RMS, not a spike
    # (a 5 kHz probe's near-end-of-life inspections: steps 1.47 of the nominal RMS at a calibrated 1.35)
    assert "spikes" not in calibrated.current_reasons(m, 1.4 * NOMINAL, 0.0, near)
    assert "spikes" in calibrated.current_reasons(m, 1.4 * spiked, 0.0, near)
    # smooth records below SPIKE_STEP keep it; nothing near nominal: nothing to calibrate
    smooth = torch.sin(torch.linspace(0.0, 6.0, N, dtype=torch.float64))[None]
    assert calibrate_spike_step(contract_model(smooth[0]), smooth, near[None]) == SPIKE_STEP
    assert calibrate_spike_step(m, signals[2:], heavy[None]) is None
    assert calibrate_spike_step(SimpleNamespace(nominal_record=NOMINAL), signals, k_hat) is None  # no intervals
