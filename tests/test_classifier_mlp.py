"""MLP health classifier and the input warp: learning, determinism, smoothness at k = 0, persistence through
the bundle, TorchScript (alone and inside the online pipeline), calibration, errors; the warp leaves the
paper's polynomial SVM (warp=none) unchanged."""

from __future__ import annotations

import pytest
import torch
from surrogate_data import faults, health

from phm_torch.online import OnlinePipeline
from phm_torch.params import load_actuator
from phm_torch.prognostics import DamageModel
from phm_torch.surrogates import FDIMLP, POD, GappyPOD, SurrogateBundle, confusion
from phm_torch.surrogates.classifiers import CLASSIFIERS, RBFSVM, MLPClassifier, PolynomialSVM, build_classifier
from phm_torch.surrogates.classifiers.base import WARP_EPS, warp_inputs
from phm_torch.surrogates.classifiers.polynomial_svm import monomial_map

pytestmark = pytest.mark.torchscript  # scripts, saves or loads TorchScript on purpose

SMALL = {"hidden": [32, 32], "epochs": 40, "batch_size": 128, "lr": 3e-3}


def importance_like(n: int, seed: int) -> torch.Tensor:
    """(n, 8) fault vectors u^4, u uniform: most entries near 0, like the importance-sampled store."""
    return torch.rand(n, 8, generator=torch.Generator().manual_seed(seed), dtype=torch.float64) ** 4


def sqrt_rule(k: torch.Tensor) -> torch.Tensor:
    """Healthy iff sqrt(k1) + sqrt(k2) + k3 < 0.6 (about 1/3 healthy): curved near k = 0."""
    return (k[:, 0].sqrt() + k[:, 1].sqrt() + k[:, 2]) < 0.6


@pytest.fixture(scope="module")
def split() -> tuple[torch.Tensor, ...]:
    k, kv = importance_like(3000, 0), importance_like(2000, 1)
    return k, sqrt_rule(k), kv, sqrt_rule(kv)


@pytest.fixture(scope="module")
def mlp(split) -> MLPClassifier:
    k, h, _, _ = split
    return MLPClassifier(**SMALL).fit(k, h)


def test_mlp_learns_a_boundary_the_polynomial_kernels_miss(mlp, split):
    k, h, kv, hv = split
    acc = confusion(mlp.predict(kv), hv)["accuracy"]
    linear = confusion(PolynomialSVM(degree=1, C=100.0).fit(k, h).predict(kv), hv)["accuracy"]
    cubic = confusion(PolynomialSVM(C=100.0).fit(k, h).predict(kv), hv)["accuracy"]
    assert acc >= 0.98
    assert linear < 0.965 and cubic < acc - 0.01
    score = mlp(kv)
    assert score.shape == (2000,) and score.dtype == torch.float64
    assert float(score[hv].mean()) > 0 > float(score[~hv].mean())
    assert mlp.n_epochs_ == 40 and len(mlp.train_loss_) == 40 and mlp.train_loss_[-1] < mlp.train_loss_[0]


def test_sqrt_warp_linearises_a_sqrt_boundary():
    k, kv = importance_like(3000, 2), importance_like(2000, 3)

    def rule(x: torch.Tensor) -> torch.Tensor:
        return x[:, :3].sqrt().sum(1) < 0.8

    h, hv = rule(k), rule(kv)
    raw = confusion(PolynomialSVM(degree=1, C=100.0).fit(k, h).predict(kv), hv)["accuracy"]
    warped = confusion(PolynomialSVM(degree=1, C=100.0, warp="sqrt").fit(k, h).predict(kv), hv)["accuracy"]
    rbf = RBFSVM(n_landmarks=100, C=100.0, warp="sqrt").fit(k, h)
    assert warped >= 0.98 and raw <= 0.95
    assert confusion(rbf.predict(kv), hv)["accuracy"] >= 0.97
    x = torch.tensor([[0.0, 0.25, 1.0, -1.0, 0, 0, 0, 0]], dtype=torch.float64)
    torch.testing.assert_close(
        warp_inputs(x, "sqrt")[0, :4], torch.tensor([0.0, 0.25, 1.0, 0.0], dtype=torch.float64).add(WARP_EPS).sqrt()
    )
    assert warp_inputs(x, "none") is x


def test_mlp_fit_is_deterministic(split, mlp):
    k, h, kv, _ = split
    again = MLPClassifier(**SMALL).fit(k, h)
    assert torch.equal(again.flat_weights, mlp.flat_weights) and torch.equal(again(kv), mlp(kv))
    other = MLPClassifier(**{**SMALL, "seed": 1}).fit(k, h)
    assert not torch.equal(other.flat_weights, mlp.flat_weights)


@pytest.mark.parametrize(
    "make",
    [
        lambda: MLPClassifier(**{**SMALL, "dtype": "float64"}),
        lambda: PolynomialSVM(C=100.0, warp="sqrt"),
        lambda: RBFSVM(n_landmarks=100, C=100.0, warp="sqrt"),
    ],
    ids=["mlp", "poly_svm", "rbf_svm"],
)
def test_sqrt_warped_score_is_differentiable_at_zero(make, split):
    k, h, kv, _ = split
    clf = make().fit(k, h)
    x = torch.zeros(3, 8, dtype=torch.float64)
    x[1, :4] = kv[1, :4]
    x[2] = kv[2]
    x.requires_grad_(True)
    (grad,) = torch.autograd.grad(clf(x).sum(), x)
    assert torch.isfinite(grad).all() and grad[0].abs().sum() > 0
    # smooth away from the boundary of [0, 1]^8 too (finite differences agree with autograd)
    assert torch.autograd.gradcheck(clf, (kv[:3].clone().requires_grad_(True),))


def test_mlp_dtypes(split, mlp):
    _, _, kv, _ = split
    assert mlp.flat_weights.dtype == torch.float32
    torch.testing.assert_close(mlp(kv.float()), mlp(kv))  # inputs are cast to float32
    double = MLPClassifier(**SMALL)
    double.load_state_dict(mlp.state_dict())
    double = double.double()
    torch.testing.assert_close(double(kv), mlp(kv), rtol=1e-5, atol=1e-5)


def test_mlp_scripts_alone_and_inside_the_online_pipeline(mlp, split):
    _, _, kv, _ = split
    scripted = torch.jit.script(mlp)
    assert torch.equal(scripted(kv), mlp(kv)) and torch.equal(scripted(kv.float()), mlp(kv.float()))

    n_full, n_modes = 401, 4
    t = torch.linspace(0, 1, n_full, dtype=torch.float64)
    modes = torch.linalg.qr(torch.stack([torch.sin((i + 1) * 3.0 * t + i) for i in range(n_modes)], 1))[0]
    mean = 1.0 + 0.5 * torch.sin(9 * t)
    gappy = GappyPOD(modes, mean, torch.linspace(0, n_full - 1, 12).round().long())
    f = torch.diag(torch.tensor([5e-4] * 6 + [0.0, 3e-4], dtype=torch.float64))
    damage = DamageModel(
        f.tolist(), [1e-6] * 6 + [0.0, 1e-6], 100.0, 20000.0, 50.0, list(load_actuator().nominal_faults)
    )
    pipe = OnlinePipeline(
        gappy,
        FDIMLP(n_modes, 6).double(),
        mlp,
        damage,
        torch.tensor([0.02, 0.0, -0.02]),
        torch.tensor([1.0] * 6 + [0.0, 1.0]),
        n_full,
        residual_threshold=0.05,
    ).eval()
    x = mean + torch.randn(5, n_modes, generator=torch.Generator().manual_seed(0), dtype=torch.float64) @ modes.T
    for a, b in zip(torch.jit.script(pipe)(x), pipe(x)):
        torch.testing.assert_close(a, b, equal_nan=True)


def test_mlp_round_trips_through_the_bundle(tmp_path, split):
    k, h, kv, _ = split
    clf = MLPClassifier(epochs=2, seed=3).fit(k, h).calibrate(k, h, 0.01)  # default layout, moved threshold
    snapshots = torch.randn(30, 50, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    pod = POD(3).fit(snapshots)
    bundle = SurrogateBundle(pod, torch.arange(0, 50, 10), FDIMLP(3, 5), clf, 20000.0)
    back = SurrogateBundle.load(bundle.save(tmp_path / "surrogates.pt"))
    assert isinstance(back.classifier, MLPClassifier) and back.classifier.get_params() == clf.get_params()
    assert torch.equal(back.health_score(kv), bundle.health_score(kv))
    assert torch.equal(back.is_healthy(kv), bundle.is_healthy(kv))
    assert float(back.classifier.threshold) == float(clf.threshold)
    twin = build_classifier("mlp", **clf.get_params())  # the registry path alone
    for name, value in clf.state_dict().items():
        setattr(twin, name, value)
    assert torch.equal(twin(kv), clf(kv))


def test_calibrate_trades_missed_faults_for_false_alarms(split):
    k, h, kv, hv = split
    clf = MLPClassifier(**{**SMALL, "epochs": 10}).fit(k, h)
    before = confusion(clf.predict(kv), hv)
    clf.calibrate(k, h, 0.0)
    assert float(clf.threshold) >= 0.0 and confusion(clf.predict(k), h)["missed_fault_rate"] == 0.0
    after = confusion(clf.predict(kv), hv)
    assert after["missed_fault_rate"] <= before["missed_fault_rate"]
    assert after["false_alarm_rate"] >= before["false_alarm_rate"]


@pytest.mark.parametrize(
    "field,value",
    [
        ("hidden", []),
        ("hidden", [16, 0]),
        ("hidden", "128"),
        ("hidden", [True]),
        ("warp", "log"),
        ("epochs", 0),
        ("batch_size", 1.5),
        ("lr", 0.0),
        ("weight_decay", -1e-4),
        ("schedule", "step"),
        ("class_weight", "auto"),
        ("seed", "zero"),
        ("dtype", "float16"),
    ],
)
def test_mlp_bad_args_name_the_field(field, value):
    with pytest.raises(ValueError, match=f"classifier.{field}"):
        MLPClassifier(**{field: value})


def test_bad_warp_and_training_set():
    assert sorted(CLASSIFIERS) == ["mlp", "poly_svm", "rbf_svm"]
    for cls in (PolynomialSVM, RBFSVM):
        with pytest.raises(ValueError, match="classifier.warp"):
            cls(warp="sqrt2")
    k = importance_like(50, 0)
    with pytest.raises(ValueError, match="both classes"):
        MLPClassifier(**SMALL).fit(k, torch.zeros(50, dtype=torch.bool))
    with pytest.raises(ValueError, match=r"k must be \(B, 8\)"):
        MLPClassifier(**SMALL)(k[:, :3])


# Scores of PolynomialSVM(C=100) fitted on faults(1500, 0) ** 2, health(...) at faults(8, 1), computed with the
# code before the warp was introduced.
BEFORE_WARP = [
    8.92975394899765,
    -1.3344709662231473,
    -12.921276825829612,
    -4.542713950628663,
    -17.675366618923817,
    10.879284512196353,
    6.363403245376157,
    -9.818075583622875,
]


def test_poly_svm_without_warp_is_unchanged():
    k, kv = faults(1500, 0) ** 2, faults(8, 1)
    clf = PolynomialSVM(C=100.0).fit(k, health(k))
    assert clf.warp == "none" and clf.get_params()["warp"] == "none"
    # L-BFGS stops at max_iter on this ill-conditioned squared hinge (165 cubic features, C = 100): its end
    # point moves by up to 0.2 % between BLAS builds of the same torch version, not with the code
    torch.testing.assert_close(clf(kv), torch.tensor(BEFORE_WARP, dtype=torch.float64), rtol=5e-3, atol=0.05)
    # bit for bit the pre-warp feature map and standardisation (raw k)
    assert torch.equal(clf.k_mean, k.mean(0)) and torch.equal(clf.k_std, k.std(0).clamp(min=1e-12))
    idx, coef = monomial_map(8, 3, 1.0 / 8, 1.0)
    z = (kv - clf.k_mean) / clf.k_std
    u = torch.cat([torch.ones_like(z[:, :1]), z], dim=1)
    assert torch.equal(clf.features(kv), coef * u[:, idx].prod(-1))
    # a classifier saved before the warp existed (params without "warp") rebuilds as warp=none
    old = {key: v for key, v in clf.get_params().items() if key != "warp"}
    assert PolynomialSVM(**old).warp == "none" and RBFSVM().warp == "none"
