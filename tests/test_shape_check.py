"""The input contract's ``shape`` check: a near-nominal answer's record must correlate with the nominal record, at
a threshold phm-evaluate calibrates per pipeline (never stricter than SHAPE_MIN)."""

from __future__ import annotations

import math
from types import SimpleNamespace

import pytest
import torch
from contract_model import contract_model

from phm_torch.online.input_contract import SHAPE_MARGIN, SHAPE_MIN, InputContract, calibrate_shape_min

N = 2000
T = torch.linspace(0.0, 1.0, N, dtype=torch.float64)
NOMINAL = torch.sin(2 * math.pi * 5 * T * T) * (T > 0.05)


def model() -> SimpleNamespace:
    return contract_model(NOMINAL)


def record(mix: float) -> torch.Tensor:
    """The nominal record blended with another waveform: correlation falls as mix grows."""
    return (1 - mix) * NOMINAL + mix * torch.cos(2 * math.pi * 3 * T)


def test_the_threshold_is_the_lowest_held_out_correlation_widened_and_never_above_shape_min():
    m = model()
    near = torch.tensor([0.0] * 6 + [0.5, 0.5], dtype=torch.float64)
    heavy = near.clone()
    heavy[2] = 0.9  # a large fault: its record is not compared with the nominal one
    signals = torch.stack([record(0.0), record(0.2), record(0.45), record(0.9)])
    k_hat = torch.stack([near, near, near, heavy])
    corr = torch.corrcoef(torch.stack([record(0.45), NOMINAL]))[0, 1].item()
    assert corr < SHAPE_MIN  # a near-nominal record of this pipeline below the reference's threshold
    got = calibrate_shape_min(m, signals, k_hat)
    assert got == pytest.approx(1 - SHAPE_MARGIN * (1 - corr))
    assert calibrate_shape_min(m, signals[:2], k_hat[:2]) == SHAPE_MIN  # records all above it: kept
    assert calibrate_shape_min(m, signals[3:], k_hat[3:]) is None  # nothing near nominal to calibrate on
    # the contract reads it from the pipeline's metadata: that record is no longer refused; a stranger one still is
    strict, own = InputContract.of(m, {}, None), InputContract.of(m, {"shape_correlation_min": got}, None)
    assert own.shape_min == got and strict.shape_min == SHAPE_MIN
    x = record(0.45)
    assert "shape" in strict.current_reasons(m, x, 0.0, near) and "shape" not in own.current_reasons(m, x, 0.0, near)
    assert "shape" in own.current_reasons(m, record(0.95), 0.0, near)
    assert InputContract.of(m, {"shape_correlation_min": 0.99}, None).shape_min == SHAPE_MIN  # never stricter


def test_the_thresholds_calibrate_on_records_near_nominal_in_truth_not_only_in_the_answer():
    """A faulty record the FDI misreads as near nominal is what the shape check exists to refuse; calibrating on it
    would lower the threshold below that record's correlation (a 28 V ball-screw sketch's fell to -0.58)."""
    from phm_torch.pipelines.evaluate.near_nominal import near_nominal_rows

    m = model()
    near = torch.tensor([0.0] * 6 + [0.5, 0.5], dtype=torch.float64)
    heavy = near.clone()
    heavy[2] = 0.9
    signals = torch.stack([record(0.0), record(0.1), record(0.9)])
    k_hat = torch.stack([near, near, near])  # all three answered near nominal ...
    k_true = torch.stack([near, near, heavy])  # ... the third wrongly
    rows = near_nominal_rows(m, k_true, torch.zeros(3, dtype=torch.bool))
    assert rows.tolist() == [True, True, False]
    assert not near_nominal_rows(m, k_true, torch.tensor([True, False, False]))[0]  # out of distribution: left out
    widened = calibrate_shape_min(m, signals, k_hat)
    own = calibrate_shape_min(m, signals[rows], k_hat[rows])
    misread = torch.corrcoef(torch.stack([record(0.9), NOMINAL]))[0, 1].item()
    assert widened < misread < own  # the misread record passes the widened check and is refused by the right one
    assert "shape" in InputContract.of(m, {"shape_correlation_min": own}, None).current_reasons(
        m, record(0.9), 0.0, near
    )


class _Answering:
    """A contract model that also answers records: k_hat near nominal, none out of distribution."""

    def __init__(self) -> None:
        self.__dict__.update(vars(model()))
        self.times = T
        self.read: list[list[int]] = []

    def __call__(self, x: torch.Tensor) -> tuple[torch.Tensor, ...]:
        b = x.shape[0]
        return self.nominal.repeat(b, 1), torch.zeros(b), None, torch.zeros(b, dtype=torch.bool), torch.zeros(b)

    def training(self, rows: list[int]) -> torch.Tensor:
        self.read.append(rows)
        return torch.stack([record(0.05 * i) for i in rows])


def test_too_few_held_out_records_near_nominal_take_the_training_splits_too():
    """A robust actuator's store holds few held-out records near nominal (a ball-screw sketch: 1 of 100); a shape
    threshold read off one record refused a fifth of its own clean life inspections. Below NEAR_MIN_ROWS the training
    split's records near nominal in truth are added; never those with a large fault, never beyond the drive range."""
    from phm_torch.pipelines.evaluate.near_nominal import NEAR_MIN_ROWS, near_nominal_calibration

    m = _Answering()
    near = m.nominal
    heavy = near.clone()
    heavy[1] = 0.9
    held = SimpleNamespace(
        signals=record(0.05)[None], k=near[None], k_hat=near[None], ood=torch.zeros(1, dtype=torch.bool)
    )
    n = NEAR_MIN_ROWS + 5
    training_k = torch.stack([heavy if i % 5 == 0 else near for i in range(n)])  # every fifth: a large fault
    got = near_nominal_calibration(m, held, training_k, m.training, 0.0, 0)
    expected = [i for i in range(n) if i % 5]
    assert m.read == [expected] and (got.held_out, got.training) == (1, len(expected))
    assert got.signals.shape == (1 + len(expected), N)
    alone = calibrate_shape_min(m, held.signals, held.k_hat)
    pooled = calibrate_shape_min(m, got.signals, got.k_hat)
    worst = torch.corrcoef(torch.stack([record(0.05 * expected[-1]), NOMINAL]))[0, 1].item()
    assert pooled == pytest.approx(1 - SHAPE_MARGIN * (1 - worst)) and pooled < alone  # the pooled loosest record
    # enough held-out records: the training split is not read
    m.read.clear()
    many = SimpleNamespace(
        signals=record(0.05)[None].repeat(NEAR_MIN_ROWS, 1),
        k=near.repeat(NEAR_MIN_ROWS, 1),
        k_hat=near.repeat(NEAR_MIN_ROWS, 1),
        ood=torch.zeros(NEAR_MIN_ROWS, dtype=torch.bool),
    )
    got = near_nominal_calibration(m, many, training_k, m.training, 0.0, 0)
    assert m.read == [] and (got.held_out, got.training) == (NEAR_MIN_ROWS, 0)
    # training records beyond the drive range are left out
    got = near_nominal_calibration(m, held, training_k, m.training, 0.0, 0, drive_bound=1.2)
    kept = [i for i in expected if float(record(0.05 * i).abs().max()) <= 1.2]
    assert 0 < len(kept) < len(expected) and got.training == len(kept)


def test_too_few_records_near_nominal_in_all_are_named_in_a_warning(caplog):
    from phm_torch.pipelines.evaluate.near_nominal import near_nominal_calibration

    m = _Answering()
    held = SimpleNamespace(
        signals=record(0.05)[None], k=m.nominal[None], k_hat=m.nominal[None], ood=torch.zeros(1, dtype=torch.bool)
    )
    with caplog.at_level("WARNING"):
        got = near_nominal_calibration(m, held, None, None, 0.01, 0)
    assert (got.held_out, got.training) == (1, 0)
    assert "calibrated on 1 records near nominal in truth" in caplog.text
