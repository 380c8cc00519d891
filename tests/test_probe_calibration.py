"""The bench's probe calibration (phm_torch/online/probe_calibration.py): a gain and offset read off its healthy
record where an affine map explains that record's difference from the nominal one, nothing where a physical
difference does (a structured residual) or where there is nothing to correct; phm-predict reads every record of such
a bench through the inverse map, and its answer is the clean bench's."""

from __future__ import annotations

import math
from pathlib import Path

import pytest
import torch

from phm_torch.online.probe_calibration import EXPLAINED_MIN, ProbeCalibration, fit_probe

PIPELINE = Path(__file__).resolve().parents[1] / "pretrained" / "online_surrogates_best.pt"


def _nominal(n: int = 4001) -> torch.Tensor:
    t = torch.arange(n, dtype=torch.float64) / 20000.0
    return 0.2 + torch.sin(2 * math.pi * (5 + 40 * t) * t) * (1 + t)  # a chirp-like current with a mean


def test_a_probe_error_is_read_off_the_healthy_record_and_undone():
    nominal = _nominal()
    rms = float(nominal.pow(2).mean().sqrt())
    g = torch.Generator().manual_seed(0)
    noise = 0.01 * rms * torch.randn(nominal.numel(), generator=g, dtype=torch.float64)
    measured = 1.05 * (nominal + noise) + 0.05 * rms
    measured[::50] = float("nan")  # missing samples are left out
    probe = fit_probe(measured, nominal)
    assert isinstance(probe, ProbeCalibration) and probe.explained >= EXPLAINED_MIN
    assert probe.gain == pytest.approx(1.05, abs=2e-3) and probe.offset == pytest.approx(0.05 * rms, abs=2e-3 * rms)
    back = probe.apply(measured)
    present = torch.isfinite(back)
    assert float((back - nominal - noise)[present].abs().max()) < 0.01 * rms  # the record as the model's probe reads it
    assert "gain 1.05" in probe.message() and probe.as_dict()["gain"] == probe.gain


def test_no_calibration_for_a_physical_difference_a_small_one_or_a_gain_no_probe_has():
    nominal = _nominal()
    t = torch.arange(nominal.numel(), dtype=torch.float64) / 20000.0
    rms = float(nominal.pow(2).mean().sqrt())
    structured = nominal + 0.05 * rms * torch.sign(torch.sin(2 * math.pi * 30 * t))  # e.g. a friction difference
    assert fit_probe(structured, nominal) is None
    partly = 1.03 * nominal + 0.03 * rms * torch.cos(2 * math.pi * 60 * t)  # part gain, part not: 66 % explained
    assert fit_probe(partly, nominal) is None
    assert fit_probe(1.003 * nominal + 0.001 * rms, nominal) is None  # nothing worth correcting
    assert fit_probe(3.0 * nominal, nominal) is None  # x3: no probe calibration error (the checks refuse it)
    assert fit_probe(nominal, None) is None and fit_probe(nominal[:-1], nominal) is None


@pytest.mark.torchscript
def test_phm_predict_reads_a_bench_through_its_probe(compose, tmp_path):
    """A bench whose probe reads x1.05 with a zero 5 % of the RMS current off: its healthy record was 13 interval
    half-widths from nominal (every record refused, ``bench``); calibrated, a record answers as the clean bench's."""
    from phm_torch.apps.predict import predict

    module = torch.jit.load(str(PIPELINE))
    nominal = module.nominal_record.double()
    rms = float(nominal.pow(2).mean().sqrt())
    t = torch.arange(nominal.numel(), dtype=torch.float64) / 20000.0
    g = torch.Generator().manual_seed(2)
    healthy = nominal + 0.01 * rms * torch.randn(nominal.numel(), generator=g, dtype=torch.float64)
    measured = 1.02 * nominal + 0.01 * rms * torch.randn(nominal.numel(), generator=g, dtype=torch.float64)

    def csv(name, x):
        path = tmp_path / name
        path.write_text("time,current\n" + "\n".join(f"{a!r},{b!r}" for a, b in zip(t.tolist(), x.tolist())) + "\n")
        return path

    answers = {}
    for name, probe in (("clean", lambda x: x), ("probe", lambda x: 1.05 * x + 0.05 * rms)):
        base, rec = csv(f"base_{name}.csv", probe(healthy)), csv(f"rec_{name}.csv", probe(measured))
        metrics, out = predict(
            compose("predict", [f"pipeline={PIPELINE}", f"measurements=[{rec}]", f"baseline=[{base}]"])
        )
        answers[name] = (metrics, out["records"][0])
    (clean_metrics, clean), (probe_metrics, probed) = answers["clean"], answers["probe"]
    assert clean_metrics["probe_calibration"] is None and clean_metrics["bench_check"]["ok"]
    assert probe_metrics["probe_calibration"]["gain"] == pytest.approx(1.05, abs=2e-3)
    assert probe_metrics["bench_check"]["ok"] and not probed["out_of_distribution"]
    assert probed["healthy"] == clean["healthy"]
    assert probed["k_hat"] == pytest.approx(clean["k_hat"], abs=5e-3)
