"""The bench check (phm_torch/online/bench_check.py): a bench's healthy record read as measured by the shipped
pipeline; a bench too far from the training model flags every record with the reason ``bench``."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch

from phm_torch.online.bench_check import BENCH_TOLERANCE, check_bench
from phm_torch.online.corruptions import Record
from phm_torch.online.diagnosis import diagnose
from phm_torch.online.input_contract import InputContract

pytestmark = pytest.mark.torchscript  # scripts, saves or loads TorchScript on purpose

PIPELINE = Path(__file__).resolve().parents[1] / "pretrained" / "online_surrogates_best.pt"


@pytest.fixture(scope="module")
def model():
    torch.set_num_threads(1)
    return torch.jit.load(str(PIPELINE))


def test_the_training_models_own_healthy_record_passes_and_a_distorted_one_does_not(model):
    nominal = model.nominal_record.double()
    own = check_bench(model, nominal)
    assert own.ok and own.healthy and own.max_deviation < 3.0  # nominal within its intervals
    assert set(own.as_dict()["deviation_half_widths"]) == set(own.as_dict()["k_hat"]) - {"eccentricity_phase"}
    # a bench whose current is 25 % larger at rest and in motion: a different motor, not a baseline offset
    other = check_bench(model, 1.25 * nominal)
    assert not other.ok and other.max_deviation > BENCH_TOLERANCE
    assert other.worst in other.message() and "phm-workbench" in other.message()


def test_a_failed_bench_check_flags_every_record_with_its_reason(model):
    nominal = model.nominal_record.double()
    t = torch.arange(nominal.numel(), dtype=torch.float64) / 20000.0
    record = Record(t, None, None, nominal.clone())
    contract = InputContract.of(model, {}, None)
    bad = check_bench(model, 1.25 * nominal)
    good = check_bench(model, nominal)
    flagged = diagnose(model, record, contract, 1.25 * nominal, bad)
    passed = diagnose(model, record, contract, nominal, good)
    assert flagged["out_of_distribution"] and "bench" in flagged["ood_reasons"]
    assert flagged["rul_hours"] is None and any("baseline record" in m for m in flagged["messages"])
    assert not passed["out_of_distribution"] and "bench" not in passed["ood_reasons"]
