"""The online RUL event search: the scan + bisection default against the exhaustive first crossing, the traced
(unblocked) scoring against the blocked one, and the full-record check's one-gather statistics."""

from __future__ import annotations

import pytest
import torch

from phm_torch.online import OnlinePipeline
from phm_torch.params import load_actuator
from phm_torch.prognostics import DamageModel
from phm_torch.surrogates.classifiers.polynomial_svm import PolynomialSVM
from phm_torch.surrogates.fdi_mlp import FDIMLP
from phm_torch.surrogates.full_signal_check import FullSignalCheck
from phm_torch.surrogates.gappy_pod import GappyPOD

N_FULL, N_MODES = 2001, 6
NOMINAL = list(load_actuator().nominal_faults)


def _pipeline(coarse: int | None) -> OnlinePipeline:
    g = torch.Generator().manual_seed(0)
    t = torch.linspace(0, 1, N_FULL, dtype=torch.float64)
    modes = torch.linalg.qr(torch.stack([torch.sin((i + 1) * 3.0 * t + i) for i in range(N_MODES)], 1))[0]
    gappy = GappyPOD(modes, 1.0 + 0.5 * torch.sin(9 * t), torch.linspace(0, N_FULL - 1, 24).round().long())
    k = torch.rand(400, 8, generator=g, dtype=torch.float64) ** 3
    k[:, 6:] = 0.5
    clf = PolynomialSVM(degree=2).fit(k, k[:, :6].amax(1) < 0.3)
    f = torch.diag(torch.tensor([5e-4] * 6 + [0.0, 3e-4], dtype=torch.float64))
    damage = DamageModel(f.tolist(), [1e-6] * 6 + [0.0, 1e-6], 100.0, 20000.0, 50.0, NOMINAL)
    deltas, direction = torch.tensor([0.02, 0.0, -0.02]), torch.tensor([1.0] * 6 + [0.0, 1.0])
    pipe = OnlinePipeline(
        gappy, FDIMLP(N_MODES, 10).double(), clf, damage, deltas, direction, N_FULL, 0.05, coarse=coarse
    )
    return pipe.eval()


@pytest.fixture(scope="module")
def vectors() -> torch.Tensor:
    g = torch.Generator().manual_seed(3)
    k = 0.25 * torch.rand(600, 8, generator=g, dtype=torch.float64) ** 2
    k[:, 6] = 0.5
    k[:, 7] = 0.5 + 0.1 * (torch.rand(600, generator=g, dtype=torch.float64) - 0.5)
    return k


def test_default_search_scans_a_quarter_of_the_grid_and_bisects_to_one_step():
    pipe = _pipeline(None)
    n_t = pipe.times.shape[0]
    assert pipe.coarse == -(-(n_t - 1) // 4) and pipe.coarse_index.numel() == 5
    assert 2 ** (pipe.bisections - 1) < pipe.coarse <= 2**pipe.bisections  # down to one grid step
    with pytest.raises(ValueError, match="online.coarse"):
        _pipeline(0)


def test_scan_search_finds_the_exhaustive_first_crossing(vectors):
    exhaustive, default = _pipeline(1), _pipeline(None)  # coarse=1: every grid point scored
    shift = default.deltas.view(3, 1) * default.direction
    with torch.no_grad():
        ref = exhaustive.rul_shifted(vectors, shift)
        fast = default.rul_shifted(vectors, shift)
        # trajectories whose score turns faulty at most once on the grid: the search's assumption
        dk = (vectors - default.nominal).abs().unsqueeze(1) + shift.unsqueeze(0)
        dk = torch.where(vectors - default.nominal >= 0, 1.0, -1.0).unsqueeze(1) * dk.clamp(min=0)
        traj = default.nominal + torch.einsum("tij,bqj->tbqi", default.propagators, dk)
        faulty = default._stop_scores(traj.reshape(-1, 3, 8), False, True).reshape(traj.shape[:3]) <= 0
    once = ~(faulty.int().cummax(0).values.bool() & ~faulty).any(0)
    crossing = once & faulty.any(0) & ~faulty[0]
    assert int(crossing.sum()) > 300  # the test exercises the bisection, not only the trivial ends
    torch.testing.assert_close(fast[once], ref[once], rtol=0, atol=1e-6 * float(default.times[-1]))
    assert int(once.sum()) == once.numel()  # a growing trajectory crosses this classifier's boundary once


def test_traced_scoring_per_scan_point_equals_the_blocked_search(vectors):
    pipe = _pipeline(None)
    with torch.no_grad():
        for measured in (False, True):
            blocked = pipe.rul(vectors, measured, blocked=True)
            traced = pipe.rul(vectors, measured, blocked=False)
            torch.testing.assert_close(traced, blocked, rtol=1e-9, atol=1e-9)


@pytest.mark.torchscript
def test_classifiers_of_different_dtypes_stop_one_propagation_together(vectors):
    """A verdict classifier in float32 beside a float64 health classifier (a refit in another dtype): the health
    stops mix their scores in one propagation (index_copy), so the search casts both to the health classifier's
    score dtype; the RUL equals the float64 pipeline's within the float32 scores' rounding."""
    import copy

    ref = _pipeline(None)
    ref.set_health_stop([2])
    mixed = copy.deepcopy(ref)
    mixed.verdict_classifier = copy.deepcopy(ref.classifier).float()
    with torch.no_grad():
        expected = ref.rul(vectors, measured=True)
        got = mixed.rul(vectors, measured=True)
    assert got.dtype == expected.dtype == torch.float64
    assert float((got - expected).abs().max()) <= float(ref.times[1] - ref.times[0])  # within one grid step
    assert float((got - expected).abs().median()) < 0.05  # hours: the crossing interpolated from float32 scores


@pytest.mark.torchscript  # scripts the check on purpose
def test_full_record_statistics_from_one_gather_equal_the_three_checks():
    g = torch.Generator().manual_seed(1)
    t = torch.linspace(0, 1, N_FULL, dtype=torch.float64)
    modes = torch.linalg.qr(torch.stack([torch.sin((i + 1) * 3.0 * t + i) for i in range(N_MODES)], 1))[0]
    mean = 1.0 + 0.5 * torch.sin(9 * t)
    check = FullSignalCheck(modes, mean, residual_threshold=0.1, plateau_threshold=0.05)  # 126 samples used
    x = mean + torch.randn(16, N_MODES, generator=g, dtype=torch.float64) @ modes.T
    x[3] += 0.3 * torch.randn(N_FULL, generator=g, dtype=torch.float64)  # rough
    x[5] = x[5].clamp(max=float(x[5].quantile(0.6)))  # clipped
    x[7, 100] = float("nan")
    residual, roughness, plateau = check.statistics(x)
    for got, want in ((residual, check.residual(x)), (roughness, check.roughness(x)), (plateau, check.plateau(x))):
        torch.testing.assert_close(got, want, rtol=0, atol=0, equal_nan=True)
    assert bool(check(x)[3]) and bool(check(x)[5]) and not bool(check(x)[0])
    scripted = torch.jit.script(check)
    torch.testing.assert_close(scripted.statistics(x)[0], residual, rtol=0, atol=0, equal_nan=True)
