"""The verdict classifier, fitted on FDI estimates: it undoes an estimator's bias at the boundary that the
health classifier of true fault vectors cannot; the bundle saves it, the online pipeline judges by it and
stops the RUL of a measured estimate on it."""

from __future__ import annotations

import pytest
import torch

from phm_torch.online import OnlinePipeline
from phm_torch.params import load_actuator
from phm_torch.prognostics import DamageModel
from phm_torch.surrogates import POD, SurrogateBundle, confusion
from phm_torch.surrogates.classifiers.polynomial_svm import PolynomialSVM
from phm_torch.surrogates.fdi_mlp import FDIMLP
from phm_torch.surrogates.verdict_classifier import (
    calibrate_verdict_held_out,
    fit_verdict_classifier,
    noisy_estimates,
)

pytestmark = pytest.mark.torchscript  # scripts, saves or loads TorchScript on purpose


def fault_vectors(n: int, seed: int) -> tuple[torch.Tensor, torch.Tensor]:
    """(n, 8) fault vectors and their health: faulty when the damage k1 + ... + k6 reaches 1.2."""
    k = torch.rand(n, 8, generator=torch.Generator().manual_seed(seed), dtype=torch.float64) ** 3
    k[:, 6:] = 0.5
    return k, k[:, :6].sum(1) < 1.2


def shrinking_fdi(samples: torch.Tensor, level: torch.Tensor) -> torch.Tensor:
    """A biased "FDI" whose samples are the fault vector itself: damage estimated at 60 %, plus the noise."""
    k_hat = samples.clone()
    k_hat[:, :6] = 0.6 * samples[:, :6]
    return k_hat.clamp(0.0, 1.0)


def erring_fdi(std: float, seed: int):
    """``shrinking_fdi`` plus a Gaussian error of ``std``, the same on every call (seeded)."""

    def fdi(s: torch.Tensor, level: torch.Tensor) -> torch.Tensor:
        error = std * torch.randn(s.shape, generator=torch.Generator().manual_seed(seed), dtype=s.dtype)
        return (shrinking_fdi(s, level) + error).clamp(0.0, 1.0)

    return fdi


def smooth_records(n: int, seed: int) -> torch.Tensor:
    """(n, 200) smooth records, float32 as a store's: four fixed shapes with random weights."""
    t = torch.linspace(0, 1, 200)
    shapes = torch.stack([torch.sin((i + 1) * 3.0 * t + i) for i in range(4)])
    return 1.0 + torch.randn(n, 4, generator=torch.Generator().manual_seed(seed)) @ shapes


def smooth_pod() -> POD:
    """A 4-mode POD of 40 smooth records."""
    return POD(4).fit(smooth_records(40, 0))


def test_noisy_estimates_add_the_rated_noise_and_tell_the_level():
    samples = torch.ones(5000, 8, dtype=torch.float64)
    seen = []

    def fdi(s: torch.Tensor, level: torch.Tensor) -> torch.Tensor:
        seen.append(level)
        return s

    k_hat = noisy_estimates(fdi, samples, torch.full((5000,), 2.0, dtype=torch.float64), 0.05, seed=0, block_rows=1500)
    assert len(seen) == 4 and all(torch.equal(lv, torch.full_like(lv, 0.05)) for lv in seen)
    assert float((k_hat - 1).std()) == pytest.approx(0.1, rel=0.03)  # 5 % of the RMS current 2
    again = noisy_estimates(fdi, samples, torch.full((5000,), 2.0, dtype=torch.float64), 0.05, seed=0, block_rows=1500)
    assert torch.equal(again, k_hat)
    assert torch.equal(noisy_estimates(fdi, samples, torch.ones(5000, dtype=torch.float64), 0.0, seed=0), samples)
    with pytest.raises(ValueError, match="noise must be >= 0"):
        noisy_estimates(fdi, samples, torch.ones(5000, dtype=torch.float64), -0.1, seed=0)
    with pytest.raises(ValueError, match="scale"):
        noisy_estimates(fdi, samples, torch.ones(3, dtype=torch.float64), 0.0, seed=0)


def test_verdict_classifier_undoes_the_estimators_bias():
    k, healthy = fault_vectors(6000, 0)
    kv, hv = fault_vectors(3000, 1)
    truth = PolynomialSVM(degree=2).fit(k, healthy)
    verdict = fit_verdict_classifier(
        PolynomialSVM(degree=2), shrinking_fdi, k, torch.ones(len(k), dtype=torch.float64), healthy, 0.0, seed=0
    )
    k_hat = shrinking_fdi(kv, torch.zeros(len(kv)))
    on_truth, on_estimates = confusion(truth.predict(k_hat), hv), confusion(verdict.predict(k_hat), hv)
    assert confusion(truth.predict(kv), hv)["accuracy"] > 0.97  # the health classifier is good on k ...
    assert on_truth["missed_fault_rate"] > 0.3  # ... and misses faults on the estimates
    assert on_estimates["accuracy"] > 0.97 and on_estimates["missed_fault_rate"] < 0.05
    with pytest.raises(ValueError, match="healthy must be"):
        fit_verdict_classifier(PolynomialSVM(degree=2), shrinking_fdi, k, torch.ones(len(k)), healthy[:10], 0.0, 0)


def test_verdict_classifier_calibrated_to_a_missed_fault_rate():
    """calibration.max_missed_fault_rate applies to the verdict too: its threshold rises until no more than
    that fraction of the fitting faults' estimates pass, which on fresh estimates trades missed faults for
    false alarms."""
    k, healthy = fault_vectors(6000, 0)
    kv, hv = fault_vectors(3000, 1)
    ones = torch.ones(len(k), dtype=torch.float64)

    noisy_fdi = erring_fdi(0.05, 5)  # the same error on every call

    plain = fit_verdict_classifier(PolynomialSVM(degree=2), noisy_fdi, k, ones, healthy, 0.0, seed=0)
    strict = fit_verdict_classifier(
        PolynomialSVM(degree=2), noisy_fdi, k, ones, healthy, 0.0, seed=0, max_missed_fault_rate=0.002
    )
    k_fit = noisy_fdi(k, ones)
    assert float(strict.threshold) > 0.0 == float(plain.threshold)
    faults = int((~healthy).sum())
    assert confusion(strict.predict(k_fit), healthy)["missed_fault_rate"] <= 0.002 + 1.0 / faults  # a quantile
    assert confusion(plain.predict(k_fit), healthy)["missed_fault_rate"] > 0.01
    k_hat = noisy_fdi(kv, torch.zeros(len(kv)))
    before, after = confusion(plain.predict(k_hat), hv), confusion(strict.predict(k_hat), hv)
    assert after["missed_fault_rate"] < before["missed_fault_rate"]
    assert after["false_alarm_rate"] > before["false_alarm_rate"]


def test_bundle_saves_the_verdict_classifier_and_the_pipeline_judges_by_it(tmp_path):
    k, healthy = fault_vectors(2000, 2)
    truth = PolynomialSVM(degree=2).fit(k, healthy)
    verdict = PolynomialSVM(degree=2).fit(shrinking_fdi(k, torch.zeros(len(k))), healthy)
    pod = smooth_pod()
    plain = SurrogateBundle(pod, torch.arange(0, 200, 10), FDIMLP(4, 5), truth, 20000.0, 1.0)
    both = SurrogateBundle(
        pod, torch.arange(0, 200, 10), plain.network, truth, 20000.0, 1.0, verdict_classifier=verdict
    )
    kv = fault_vectors(500, 3)[0]
    assert torch.equal(plain.verdict_score(kv), plain.health_score(kv))  # no verdict classifier: f
    assert torch.equal(both.verdict_healthy(kv), verdict.predict(kv))
    assert not torch.equal(both.verdict_score(kv), both.health_score(kv))
    back = SurrogateBundle.load(both.save(tmp_path / "both.pt"))
    assert torch.equal(back.verdict_score(kv), both.verdict_score(kv))
    assert torch.equal(back.health_score(kv), both.health_score(kv))
    assert SurrogateBundle.load(plain.save(tmp_path / "plain.pt")).verdict_classifier is None

    f = torch.diag(torch.tensor([5e-4] * 6 + [0.0, 3e-4], dtype=torch.float64))
    damage = DamageModel(
        f.tolist(), [1e-6] * 6 + [0.0, 1e-6], 100.0, 20000.0, 50.0, list(load_actuator().nominal_faults)
    )
    pipe = OnlinePipeline.from_bundle(
        back, damage, torch.tensor([0.02, 0.0, -0.02]), torch.tensor([1.0] * 6 + [0.0, 1.0])
    ).eval()
    x = smooth_records(6, 1)[:, back.indices]  # samples
    with torch.no_grad():
        k_hat, score, rul, ood, _ = pipe(x)
        scripted = torch.jit.script(pipe)(x)
    assert not ood.any()
    torch.testing.assert_close(score, back.verdict_score(k_hat))  # the verdict, not f
    assert pipe.classifier is back.classifier  # the RUL event of a known k
    assert pipe.verdict_classifier is back.verdict_classifier
    for a, b in zip(scripted, (k_hat, score, rul), strict=False):
        torch.testing.assert_close(a, b, equal_nan=True)


def test_a_measured_rul_stops_on_the_verdict_and_agrees_with_it():
    k, healthy = fault_vectors(3000, 4)
    truth = PolynomialSVM(degree=2).fit(k, healthy)
    verdict = PolynomialSVM(degree=2).fit(shrinking_fdi(k, torch.zeros(len(k))), healthy)
    pod = smooth_pod()
    bundle = SurrogateBundle(
        pod, torch.arange(0, 200, 10), FDIMLP(4, 5), truth, 20000.0, 1.0, verdict_classifier=verdict
    )
    f = torch.diag(torch.tensor([5e-4] * 6 + [0.0, 3e-4], dtype=torch.float64))
    damage = DamageModel(
        f.tolist(), [1e-6] * 6 + [0.0, 1e-6], 100.0, 20000.0, 50.0, list(load_actuator().nominal_faults)
    )
    pipe = OnlinePipeline.from_bundle(bundle, damage, torch.zeros(3), torch.tensor([1.0] * 6 + [0.0, 1.0])).eval()
    k_hat = shrinking_fdi(fault_vectors(2000, 5)[0], torch.zeros(2000)).to(torch.float32)
    with torch.no_grad():
        measured, known = pipe.rul(k_hat, True), pipe.rul(k_hat, False)
        scripted = torch.jit.script(pipe).rul(k_hat, True)
    g_healthy, f_healthy = bundle.verdict_healthy(k_hat), bundle.health_score(k_hat) > 0
    assert int((g_healthy != f_healthy).sum()) > 50  # the two classifiers disagree on these
    assert torch.equal(measured[:, 1] > 0, g_healthy)  # an estimate's RUL agrees with its verdict
    assert torch.equal(known[:, 1] > 0, f_healthy)  # a known k's RUL with the health classifier
    torch.testing.assert_close(scripted, measured)
    # through forward, with a physics band that moves the median start away from k_hat: still no life left
    # at 5 and 50 % for a record the verdict calls faulty
    shifted = OnlinePipeline.from_bundle(
        bundle, damage, torch.full((3,), -0.05), torch.tensor([1.0] * 6 + [0.0, 1.0])
    ).eval()
    alpha = 3.0 * torch.randn(300, 4, generator=torch.Generator().manual_seed(6))
    samples = bundle.pod.reconstruct(alpha)[:, bundle.indices]  # in the span: in distribution
    with torch.no_grad():
        k_hat, score, rul, ood, _ = shifted(samples)
    assert not ood.any() and bool((score <= 0).any()) and bool((score > 0).any())
    assert torch.equal(rul[score <= 0, :2], torch.zeros_like(rul[score <= 0, :2]))
    assert bool((rul[score > 0, 1] > 0).all())


def test_fit_verdict_classifier_script_adds_one_to_a_trained_bundle(tmp_path):
    from surrogate_data import write_store

    from phm_torch.surrogates.data import load_store
    from phm_torch.surrogates.verdict_refit import read_samples, refit_verdict_classifier

    store = write_store(tmp_path / "store", {"train": 300, "val": 60}, noise=0.01)
    data, _, _ = load_store(str(store), {"train": "train", "val": "val"}, {})
    train = data["train"]
    pod = POD(6).fit(train.current)
    bundle = SurrogateBundle(
        pod,
        torch.linspace(0, pod.mean_.shape[0] - 1, 12).round().long(),
        FDIMLP(6, 5),
        PolynomialSVM(degree=2).fit(train.k, train.healthy),
        20000.0,
    )
    bundle.save(tmp_path / "in.pt")
    samples, scale, healthy = read_samples(bundle, str(store), "train")
    assert samples.shape == (300, 12) and torch.equal(samples, bundle.compress(train.current))
    assert torch.equal(healthy, train.healthy.bool()) and scale.shape == (300,)
    report = refit_verdict_classifier(str(tmp_path / "in.pt"), str(store), str(tmp_path / "out.pt"))
    out = SurrogateBundle.load(tmp_path / "out.pt")
    assert isinstance(out.verdict_classifier, PolynomialSVM) and report["n"] == 300
    assert set(report["val"]) == {"health_classifier", "verdict"}
    kv = torch.rand(50, 8, dtype=torch.float64)
    assert torch.equal(out.health_score(kv), bundle.health_score(kv))  # the health classifier is kept
    with pytest.raises(ValueError, match="split 'test' is not in the store"):
        refit_verdict_classifier(str(tmp_path / "in.pt"), str(store), str(tmp_path / "x.pt"), split="test")


def test_verdict_calibrated_on_held_out_estimates_keeps_its_rate_on_unseen_records():
    """An FDI errs less on the records it was fitted on than on an unseen record. Calibrated on its fitting records'
    estimates (``max_missed_fault_rate``), the verdict promises a missed-fault rate that unseen records break;
    calibrated on records held out from the FDI's fit (``calibrate_verdict_held_out``), the rate holds."""
    k, healthy = fault_vectors(6000, 0)
    k_held, h_held = fault_vectors(1500, 2)
    kv, hv = fault_vectors(4000, 1)
    ones = torch.ones(len(k), dtype=torch.float64)

    fitted_fdi = erring_fdi(0.02, 5)  # a small error on its own records

    def unseen_fdi(s: torch.Tensor, seed: int) -> torch.Tensor:  # three times that on records it never saw
        return erring_fdi(0.06, seed)(s, torch.zeros(len(s)))

    rate = 0.02
    in_sample = fit_verdict_classifier(PolynomialSVM(degree=2), fitted_fdi, k, ones, healthy, 0.0, 0, rate)
    held_out = fit_verdict_classifier(PolynomialSVM(degree=2), fitted_fdi, k, ones, healthy, 0.0, 0)
    report = calibrate_verdict_held_out(held_out, unseen_fdi(k_held, 7), h_held, rate)
    assert report["n_held_out"] == 1500 and report["n_faulty"] == int((~h_held).sum())
    missed_before, missed_after = report["held_out_missed_fault_rate"]
    assert missed_after <= rate + 1.0 / report["n_faulty"] < missed_before
    k_hat = unseen_fdi(kv, 8)
    on_unseen = {name: confusion(c.predict(k_hat), hv) for name, c in (("in", in_sample), ("held", held_out))}
    assert on_unseen["held"]["missed_fault_rate"] < 0.035  # the promised 2 %, within the held-out set's sampling
    assert on_unseen["in"]["missed_fault_rate"] > 2 * on_unseen["held"]["missed_fault_rate"]
    assert on_unseen["held"]["false_alarm_rate"] > on_unseen["in"]["false_alarm_rate"]  # the price, stated
