"""mismatch_metrics: the surrogates on records of another model, against records of their own."""

from __future__ import annotations

import math

import pytest
import torch
from surrogate_data import faults, health

from phm_torch.surrogates import FDIMLP, POD, GappyPOD, SurrogateBundle, err_k
from phm_torch.surrogates.classifiers import MLPClassifier
from phm_torch.surrogates.model_mismatch import mismatch_metrics


def smooth_records(k: torch.Tensor, n_e: int = 10001) -> torch.Tensor:
    """(B, n_e) records [A] of a rank-10 family that passes the full-record shape checks, whose thresholds
    are set for envelope currents: full length, 5-13 cycles per record (not rough, no plateau)."""
    t = torch.linspace(0.0, 1.0, n_e, dtype=torch.float64)
    shapes = torch.stack([torch.sin(2 * math.pi * (5 + i) * t + i) for i in range(9)])
    amplitudes = torch.cat([k, k[:, :1] * k[:, 1:2]], 1)
    return 3.0 + 2.0 * torch.sin(2 * math.pi * 8 * t) + amplitudes @ shapes


@pytest.fixture(scope="module")
def bundle() -> SurrogateBundle:
    torch.manual_seed(0)  # the (untrained) network's weights
    k = faults(300, seed=0)
    x = smooth_records(k)
    pod = POD(10).fit(x)
    indices = torch.arange(5, x.shape[1], 500)
    gappy = GappyPOD(pod.modes_, pod.mean_, indices)
    with torch.no_grad():
        residual = gappy(
            gappy.select(x + 0.01 * torch.randn(x.shape, generator=torch.Generator().manual_seed(1), dtype=x.dtype))
        )[1]
    network = FDIMLP(10, 8).set_normalization(gappy(gappy.select(x))[0]).double()
    clf = MLPClassifier(hidden=[16], epochs=5, seed=0).fit(k, health(k))
    return SurrogateBundle(pod, indices, network, clf, 20000.0, residual_threshold=float(residual.max()) * 1.5)


@pytest.fixture(scope="module")
def vectors() -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    k = faults(40, seed=1)
    return k, health(k), smooth_records(k)


def test_own_records_give_the_bundles_own_figures(bundle, vectors):
    k, healthy, reference = vectors
    m = mismatch_metrics(bundle, k, healthy, reference, reference.clone())
    with torch.no_grad():
        k_hat = bundle.fdi(bundle.compress(reference))
    assert m["n"] == 40 and m["nrmse_median"] == 0.0
    assert m["err_k"] == pytest.approx(err_k(k_hat.double(), k), rel=1e-12)
    verdict = bundle.verdict_healthy(k_hat)
    assert m["chain_accuracy"] == pytest.approx(float((verdict == healthy).double().mean()))
    assert m["chain_missed_fault_rate"] == pytest.approx(float(verdict[~healthy].double().mean()))
    assert m["chain_false_alarm_rate"] == pytest.approx(float((~verdict[healthy]).double().mean()))
    assert m["ood_rate"] == 0.0  # clean records of the training family


def test_difference_size_and_out_of_distribution_flags(bundle, vectors):
    k, healthy, reference = vectors
    # a slow offset of 1 % of each record's range: NRMSE exactly 0.01, still an envelope current
    spread = reference.amax(1, keepdim=True) - reference.amin(1, keepdim=True)
    shifted = mismatch_metrics(bundle, k, healthy, reference, reference + 0.01 * spread)
    assert shifted["nrmse_median"] == pytest.approx(0.01, rel=1e-9)
    assert shifted["ood_rate_full"] == 0.0
    # white noise as large as the records: rough (the full-record check) and far from the span (gappy)
    noise = reference + spread * torch.randn(
        reference.shape, generator=torch.Generator().manual_seed(0), dtype=reference.dtype
    )
    wild = mismatch_metrics(bundle, k, healthy, reference, noise)
    assert wild["ood_rate_full"] == 1.0 and wild["ood_rate_gappy"] == 1.0 and wild["ood_rate"] == 1.0
    assert wild["nrmse_median"] > 0.5


def test_bad_shapes_name_the_argument(bundle, vectors):
    k, healthy, reference = vectors
    with pytest.raises(ValueError, match="reference and signals must both be"):
        mismatch_metrics(bundle, k, healthy, reference, reference[:, :-1])
    with pytest.raises(ValueError, match=r"k must be \(40, 8\)"):
        mismatch_metrics(bundle, k[:, :7], healthy, reference, reference)
    with pytest.raises(ValueError, match=r"healthy must be \(40,\)"):
        mismatch_metrics(bundle, k, healthy[:5], reference, reference)
