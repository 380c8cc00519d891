"""Health classifiers: the exact polynomial feature map, separation, smooth score, scripting, errors."""

from __future__ import annotations

import pytest
import torch
from surrogate_data import faults, health

from phm_torch.surrogates import CLASSIFIERS, PolynomialSVM, build_classifier, confusion
from phm_torch.surrogates.classifiers.polynomial_svm import monomial_map

pytestmark = pytest.mark.torchscript  # scripts, saves or loads TorchScript on purpose


@pytest.mark.parametrize("degree,gamma,coef0", [(3, 0.125, 1.0), (2, 0.7, 0.3), (4, 1.0, 0.0)])
def test_feature_map_is_the_polynomial_kernel(degree, gamma, coef0):
    idx, coef = monomial_map(8, degree, gamma, coef0)
    x, y = torch.randn(6, 8, dtype=torch.float64), torch.randn(5, 8, dtype=torch.float64)

    def phi(z: torch.Tensor) -> torch.Tensor:
        u = torch.cat([torch.ones(z.shape[0], 1, dtype=z.dtype), z], 1)
        return coef * u[:, idx].prod(-1)

    assert torch.allclose(phi(x) @ phi(y).T, (gamma * x @ y.T + coef0) ** degree, rtol=1e-10, atol=1e-10)
    assert idx.shape[0] == (165 if (degree == 3 and coef0 > 0) else idx.shape[0])


@pytest.fixture(scope="module")
def split() -> tuple[torch.Tensor, ...]:
    k, kv = faults(1500, 0), faults(500, 1)
    return k, health(k), kv, health(kv)


@pytest.mark.parametrize("name,params", [("poly_svm", {"C": 100.0}), ("rbf_svm", {"C": 100.0, "n_landmarks": 200})])
def test_classifiers_learn_a_curved_boundary(name, params, split):
    k, h, kv, hv = split
    clf = build_classifier(name, **params).fit(k, h)
    conf = confusion(clf.predict(kv), hv)
    assert conf["accuracy"] > 0.97
    score = clf(kv)
    assert score.shape == (500,) and score.dtype == torch.float64
    assert torch.equal(clf.predict(kv), score > 0)
    # Healthy actuators score positive (the convention).
    assert float(score[hv].mean()) > 0 > float(score[~hv].mean())


def test_score_is_smooth_and_scriptable(split):
    k, h, kv, _ = split
    clf = PolynomialSVM(C=100.0).fit(k, h)
    x = kv[:4].clone().requires_grad_(True)
    assert torch.autograd.gradcheck(clf, (x,))
    scripted = torch.jit.script(clf)
    assert torch.allclose(scripted(kv.float()), clf(kv.float()))


def test_balanced_weights_reduce_missed_faults(split):
    k, h, kv, hv = split
    plain = confusion(PolynomialSVM(C=0.1).fit(k, h).predict(kv), hv)
    bal = confusion(PolynomialSVM(C=0.1, class_weight="balanced").fit(k, h).predict(kv), hv)
    assert bal["false_alarm_rate"] <= plain["false_alarm_rate"]  # the healthy minority gets more weight


def test_confusion_rates():
    pred = torch.tensor([True, True, False, False, True])
    act = torch.tensor([True, False, False, True, True])
    c = confusion(pred, act)
    assert c["missed_faults"] == 1 and c["false_alarms"] == 1
    assert c["missed_fault_rate"] == pytest.approx(1 / 2) and c["false_alarm_rate"] == pytest.approx(1 / 3)
    assert c["accuracy"] == pytest.approx(3 / 5)


def test_bad_input(split):
    k, h, _, _ = split
    assert {"poly_svm", "rbf_svm"} <= set(CLASSIFIERS)
    with pytest.raises(ValueError, match="classifier: unknown name 'knn'"):
        build_classifier("knn")
    with pytest.raises(ValueError, match="classifier.degree"):
        PolynomialSVM(degree=0)
    with pytest.raises(ValueError, match="classifier.C must be > 0"):
        PolynomialSVM(C=-1.0)
    with pytest.raises(ValueError, match="classifier.class_weight"):
        PolynomialSVM(class_weight="auto")
    with pytest.raises(ValueError, match="both classes"):
        PolynomialSVM().fit(k, torch.ones(k.shape[0], dtype=torch.bool))
    with pytest.raises(ValueError, match=r"k must be \(N, 8\)"):
        PolynomialSVM().fit(k[:, :7], h)
    clf = PolynomialSVM().fit(k, h)
    with pytest.raises(ValueError, match=r"k must be \(B, 8\)"):
        clf(k[:, :3])


def test_calibration_trades_missed_faults_for_false_alarms(split):
    k, h, kv, hv = split
    clf = PolynomialSVM(C=10.0).fit(k, h)
    before = confusion(clf.predict(kv), hv)
    clf.calibrate(k, h, 0.0)
    train = confusion(clf.predict(k), h)
    after = confusion(clf.predict(kv), hv)
    assert float(clf.threshold) >= 0.0
    assert train["missed_fault_rate"] == 0.0
    assert after["missed_fault_rate"] <= before["missed_fault_rate"]
    assert after["false_alarm_rate"] >= before["false_alarm_rate"]
    with pytest.raises(ValueError, match="calibration.max_missed_fault_rate"):
        clf.calibrate(k, h, 1.5)


@pytest.mark.parametrize("degree", [1, 2, 3, 4])
@pytest.mark.parametrize("warp", ["none", "sqrt"])
def test_dense_polynomial_score_equals_the_feature_map(degree, warp):
    """forward contracts a coefficient tensor; it must be the SVM's phi(z) . beta + b exactly."""
    g = torch.Generator().manual_seed(degree)
    k = torch.rand(600, 8, generator=g, dtype=torch.float64) ** 3
    clf = PolynomialSVM(degree=degree, C=100.0, warp=warp).fit(k, k[:, :6].amax(1).sqrt() + 0.3 * k[:, 7] < 0.6)
    ref = clf.features(k) @ clf.beta + clf.bias
    torch.testing.assert_close(clf(k), ref, rtol=1e-12, atol=1e-10)
    torch.testing.assert_close(torch.jit.script(clf)(k.float()), clf(k.float()), rtol=0, atol=0)
