"""The full-flow RUL band: calibrated on held-out estimates, it covers the true-k RUL that the physics-only
band misses when k_hat is biased and noisy."""

from __future__ import annotations

import pytest
import torch
from test_online import N_FULL, damage, pipeline  # noqa: F401  (the fixture)
from torch import nn

from phm_torch.online import OnlinePipeline
from phm_torch.online.fdi_band import TooFewCalibrationSignals, calibrate_fdi_band


class TableFDI(nn.Module):
    """k_hat looked up by the record index carried in the first POD coefficient (a controlled FDI error)."""

    def __init__(self, table: torch.Tensor):
        super().__init__()
        self.table = table

    def forward(self, alpha: torch.Tensor) -> torch.Tensor:
        return self.table[alpha[:, 0].round().long().clamp(0, self.table.shape[0] - 1)]


def case(pipe: OnlinePipeline, n: int, seed: int) -> tuple[OnlinePipeline, torch.Tensor, torch.Tensor]:
    """n records, true k near nominal, k_hat = k + a positive bias + noise (as near nominal in the paper run)."""
    g = torch.Generator().manual_seed(seed)
    k = torch.rand(n, 8, generator=g, dtype=torch.float64) * 0.08
    k[:, 6:] = 0.5
    err = 0.05 + 0.03 * torch.randn(n, 8, generator=g, dtype=torch.float64)
    err[:, 6:] = 0.0
    k_hat = (k + err).clamp(0.0, 1.0)
    alpha = torch.zeros(n, pipe.n_modes, dtype=torch.float64)
    alpha[:, 0] = torch.arange(n, dtype=torch.float64)
    records = pipe.mean_signal + alpha @ pipe.modes.T
    measured = OnlinePipeline(
        pipe.gappy,
        TableFDI(k_hat),
        pipe.classifier,
        damage(),
        pipe.deltas,
        pipe.direction,
        N_FULL,
        residual_threshold=1e3,
    ).eval()
    return measured, records, k


def coverage(pipe: OnlinePipeline, records: torch.Tensor, k: torch.Tensor) -> float:
    with torch.no_grad():
        truth = pipe.rul(k)[:, 1]
        band = pipe(records)[2]
    ok = truth > 0
    return float(((truth >= band[:, 0]) & (truth <= band[:, 2]))[ok].double().mean())


def test_band_reaches_its_coverage_on_calibration_and_on_fresh_records(pipeline):  # noqa: F811
    measured, records, k = case(pipeline, 300, seed=1)
    physics_only = coverage(measured, records, k)
    band = calibrate_fdi_band(measured, records, k)
    with torch.no_grad():
        k_hat = measured(records)[0]
    scale = (k_hat - k).abs().mean(0)
    scale[6] = 0.0  # the eccentricity phase never grows
    torch.testing.assert_close(band.direction, scale)
    assert not any(band.saturated) and band.deltas[1] == 0.0  # the median stays k_hat's own by default
    measured.fdi_deltas.copy_(band.deltas)
    measured.fdi_direction.copy_(band.direction)
    with torch.no_grad():
        torch.testing.assert_close(measured.rul(k), measured.rul(k, False))  # a known k keeps the physics band
        truth, est = measured.rul(k)[:, 1], measured(records)[2]
    ok = truth > 0
    below = float((truth[ok] < est[ok, 0]).double().mean())
    above = float((truth[ok] > est[ok, 2]).double().mean())
    # the upper bound sits at the bisection's edge; the lower one is slack (the biased median is early)
    assert below <= 0.05 + 1e-9 and 0.03 <= above <= 0.05 + 1e-9
    assert float((est[ok, 1] / truth[ok]).median()) < 0.9  # the biased k_hat: an early median
    corrected = calibrate_fdi_band(measured, records, k, correct_median=True)
    assert corrected.deltas[1] < 0  # the upward FDI bias is taken back
    measured.fdi_deltas.copy_(corrected.deltas)
    with torch.no_grad():
        est = measured(records)[2]
    assert float((est[ok, 1] / truth[ok]).median()) == pytest.approx(1.0, abs=0.05)
    measured.fdi_deltas.copy_(band.deltas)
    fresh, fresh_records, fresh_k = case(pipeline, 300, seed=2)
    fresh.fdi_deltas.copy_(band.deltas)
    fresh.fdi_direction.copy_(band.direction)
    assert physics_only < 0.5
    assert coverage(fresh, fresh_records, fresh_k) >= 0.84


def test_bad_calibration_input(pipeline):  # noqa: F811
    measured, records, k = case(pipeline, 30, seed=3)
    with pytest.raises(ValueError, match="coverage"):
        calibrate_fdi_band(measured, records, k, coverage=1.0)
    with pytest.raises(ValueError, match="k \\(N, 8\\)"):
        calibrate_fdi_band(measured, records, k[:10])
    with pytest.raises(TooFewCalibrationSignals, match="at least 40"):
        calibrate_fdi_band(measured, records, k, min_used=40)


class NominalIsFaulty(nn.Module):
    """A verdict classifier fitted on an FDI that never returns the nominal vector: it calls every k faulty."""

    def __init__(self):
        super().__init__()
        self.register_buffer("threshold", torch.tensor(0.0, dtype=torch.float64))

    def forward(self, k: torch.Tensor) -> torch.Tensor:
        return -torch.ones(k.shape[0], dtype=k.dtype)


@pytest.mark.torchscript
def test_a_verdict_that_cannot_cover_hands_the_upper_bound_to_the_health_classifier(pipeline):  # noqa: F811
    measured, records, k = case(pipeline, 300, seed=4)
    blind = OnlinePipeline(
        measured.gappy,
        measured.fdi,
        measured.classifier,
        damage(),
        measured.deltas,
        measured.direction,
        N_FULL,
        residual_threshold=1e3,
        verdict_classifier=NominalIsFaulty(),
    ).eval()
    band = calibrate_fdi_band(blind, records, k)
    # the 95 % bound could not cover under the verdict (every propagation stops at once) and switched; the 5 %
    # bound covers trivially and keeps the verdict
    assert band.health_stop == [2] and blind.health_stop_index.tolist() == [2]
    assert not band.saturated[2] and band.deltas[2] < 0
    blind.fdi_deltas.copy_(band.deltas)
    blind.fdi_direction.copy_(band.direction)
    with torch.no_grad():
        truth, est = blind.rul(k)[:, 1], blind(records)[2]
    ok = truth > 0
    assert float((est[ok, 0] == 0).double().mean()) == 1.0  # the verdict says faulty: nothing left at 5 %
    assert float((truth[ok] <= est[ok, 2]).double().mean()) >= 0.95 - 1e-9  # the switched bound covers
    # the health-stopped upper propagation is the one the health classifier would give from the same start
    shift = blind.deltas.view(3, 1) * blind.direction + band.deltas.view(3, 1).to(blind.direction) * band.direction.to(
        blind.direction
    )
    k_hat = blind(records)[0]
    torch.testing.assert_close(
        blind.rul_shifted(k_hat, shift, True)[:, 2], blind.rul_shifted(k_hat, shift, False)[:, 2]
    )
    scripted = torch.jit.script(blind)
    torch.testing.assert_close(scripted(records)[2], blind(records)[2])
    with pytest.raises(ValueError, match="fdi_health_stop"):
        blind.set_health_stop([1])


def test_an_unidentified_component_starts_the_upper_bound_at_nominal(pipeline):  # noqa: F811
    measured, records, k = case(pipeline, 60, seed=5)
    with torch.no_grad():
        k_hat = measured(records)[0]
        before = measured.rul(k_hat, True)
        measured.set_unidentified([5, 6])  # eccentricity (grows) and its phase (does not: left alone)
        after = measured.rul(k_hat, True)
        assert measured.unknown_shift[2].tolist() == [0, 0, 0, 0, 0, -1.0, 0, 0]
        assert measured.unknown_shift[:2].abs().sum() == 0
        start = k_hat.clone()
        start[:, 5] = measured.nominal[5]
        expected = measured.propagations(start, measured.fdi_deltas, measured.fdi_direction, True)[:, 2]
        torch.testing.assert_close(
            measured.propagations(k_hat, measured.fdi_deltas, measured.fdi_direction, True)[:, 2], expected
        )
        torch.testing.assert_close(after[:, 1], before[:, 1])  # the median keeps k_hat's own start
        assert bool((after[:, 2] >= before[:, 2] - 1e-6).all())  # less damage: never a shorter upper bound
        torch.testing.assert_close(measured.rul(k), measured.rul(k, False))  # a known k is not touched
        measured.set_unidentified(None)
        torch.testing.assert_close(measured.rul(k_hat, True), before)
    with pytest.raises(ValueError, match="unidentified"):
        measured.set_unidentified([8])
