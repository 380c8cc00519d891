"""The FDI alone (``OnlinePipeline.k_hat_of_samples``): for a complete record the gappy least squares and the input
scaling are folded into the network's first layer (a noise-aware network or an ensemble in two stages), equal to the
layers taken one after the other (eager and TorchScript); a missing sample or a Bayesian gappy layer take the layers
as they are."""

from __future__ import annotations

import pytest
import torch

from phm_torch.online import OnlinePipeline
from phm_torch.online.sample_fdi import FoldedFDI
from phm_torch.params import load_actuator
from phm_torch.prognostics import DamageModel
from phm_torch.surrogates.classifiers.polynomial_svm import PolynomialSVM
from phm_torch.surrogates.fdi_ensemble import FDIEnsemble
from phm_torch.surrogates.fdi_mlp import FDIMLP
from phm_torch.surrogates.gappy_pod import GappyPOD

N_FULL, N_MODES, N_POINTS = 801, 6, 20

pytestmark = pytest.mark.torchscript  # scripts the pipeline on purpose


def _pipeline(fdi: torch.nn.Module) -> tuple[OnlinePipeline, torch.Tensor]:
    g = torch.Generator().manual_seed(0)
    t = torch.linspace(0, 1, N_FULL, dtype=torch.float64)
    modes = torch.linalg.qr(torch.stack([torch.sin((i + 1) * 3.0 * t + i) for i in range(N_MODES)], 1))[0]
    mean = 1.0 + 0.5 * torch.sin(9 * t)
    gappy = GappyPOD(modes, mean, torch.linspace(0, N_FULL - 1, N_POINTS).round().long())
    alpha = 3.0 * torch.randn(300, N_MODES, generator=g, dtype=torch.float64) + 1.0
    if isinstance(fdi, FDIMLP):
        fdi.set_normalization(
            alpha, torch.rand(300, generator=g, dtype=torch.float64) * 0.05 if fdi.noise_input else None
        )
    k = torch.rand(200, 8, generator=g, dtype=torch.float64) ** 3
    k[:, 6:] = 0.5
    clf = PolynomialSVM(degree=2).fit(k, k[:, :6].amax(1) < 0.3)
    pipe = OnlinePipeline(
        gappy, fdi, clf, _damage(), torch.tensor([0.02, 0.0, -0.02]), torch.ones(8), N_FULL, residual_threshold=0.05
    ).eval()
    records = mean + alpha[:16] @ modes.T
    return pipe, records.index_select(1, gappy.indices)


def _damage() -> DamageModel:
    rates = torch.diag(torch.tensor([5e-4] * 6 + [0.0, 3e-4], dtype=torch.float64))
    nominal = list(load_actuator().nominal_faults)
    return DamageModel(rates.tolist(), [1e-6] * 6 + [0.0, 1e-6], 100.0, 20000.0, 50.0, nominal)


def _layer_by_layer(pipe: OnlinePipeline, samples: torch.Tensor) -> torch.Tensor:
    alpha, _ = pipe.gappy(samples)
    return pipe.fdi(alpha)


def test_folded_fdi_equals_the_layers_one_after_the_other_eager_and_scripted():
    torch.manual_seed(0)
    pipe, samples = _pipeline(FDIMLP(N_MODES, 12, n_layers=2).double())
    assert pipe.fdi_folded
    want = _layer_by_layer(pipe, samples)
    assert 0.0 < float(want.std())  # not all clamped
    with torch.no_grad():
        torch.testing.assert_close(pipe.k_hat_of_samples(samples), want, rtol=0, atol=1e-10)
        scripted = torch.jit.script(pipe)
        torch.testing.assert_close(scripted.k_hat_of_samples(samples), want, rtol=0, atol=1e-10)
        holed = samples.clone()
        holed[:, 3] = float("nan")  # a missing sample: the gappy layer's own path
        torch.testing.assert_close(scripted.k_hat_of_samples(holed), _layer_by_layer(pipe, holed), rtol=0, atol=0)
    assert not any(k.startswith("folded_fdi") for k in pipe.state_dict())  # derived, no new state


def _layer_by_layer_default_noise(pipe: OnlinePipeline, samples: torch.Tensor) -> torch.Tensor:
    alpha, _ = pipe.gappy(samples)
    return pipe.fdi(alpha, None)  # a noise-aware network at its default level, as k_hat_of_samples tells it


@pytest.mark.parametrize("kind", ["noise_aware", "ensemble", "noise_aware_ensemble"])
def test_noise_aware_networks_and_ensembles_fold_in_two_stages(kind):
    """The projection S (f - mean), then every member's first layer stacked into one (their input scaling and the
    default noise level folded in), the deeper layers as batched products: equal to the layers, eager and
    scripted; a missing sample takes the layers."""
    torch.manual_seed(1)
    if kind == "noise_aware":
        fdi = FDIMLP(N_MODES, 12, n_layers=2, noise_input=True).double()
    else:
        fdi = FDIEnsemble(N_MODES, 8, n_layers=2, n_members=3, noise_input=kind == "noise_aware_ensemble").double()
        g = torch.Generator().manual_seed(2)
        alpha = 3.0 * torch.randn(300, N_MODES, generator=g, dtype=torch.float64) + 1.0
        noise = torch.rand(300, generator=g, dtype=torch.float64) * 0.05 if fdi.noise_input else None
        fdi.set_normalization(alpha, noise)
    pipe, samples = _pipeline(fdi)
    assert pipe.fdi_folded and pipe.folded_fdi.two_stage
    want = _layer_by_layer_default_noise(pipe, samples)
    assert 0.0 < float(want.std())
    with torch.no_grad():
        torch.testing.assert_close(pipe.k_hat_of_samples(samples), want, rtol=0, atol=1e-10)
        scripted = torch.jit.script(pipe)
        torch.testing.assert_close(scripted.k_hat_of_samples(samples), want, rtol=0, atol=1e-10)
        holed = samples.clone()
        holed[:, 3] = float("nan")
        torch.testing.assert_close(
            scripted.k_hat_of_samples(holed), _layer_by_layer_default_noise(pipe, holed), rtol=0, atol=0
        )
    assert not any(k.startswith("folded_fdi") for k in pipe.state_dict())


def test_a_bayesian_gappy_layer_is_not_folded():
    """Its estimate depends on the noise covariance, not a fixed linear map of the samples."""
    pipe, _ = _pipeline(FDIMLP(N_MODES, 12).double())
    g = pipe.gappy
    bayes = GappyPOD(
        torch.eye(N_FULL, N_MODES, dtype=torch.float64),
        torch.zeros(N_FULL, dtype=torch.float64),
        g.indices,
        noise_covariance=torch.eye(N_POINTS, dtype=torch.float64),
        prior_variance=torch.ones(N_MODES, dtype=torch.float64),
    )
    assert not FoldedFDI(bayes, pipe.fdi).folded
