"""Online pipeline: RUL against the Monte-Carlo-free torchdiffeq reference, bad input, TorchScript export."""

from __future__ import annotations

import copy
import logging
import math
import subprocess
import sys
import textwrap

import pytest
import torch

from phm_torch.io import write_measurement
from phm_torch.online import OnlinePipeline
from phm_torch.online.export import export_torchscript
from phm_torch.params import load_actuator
from phm_torch.prognostics import DamageModel, DeterministicRUL, RULEstimator
from phm_torch.surrogates.classifiers.polynomial_svm import PolynomialSVM
from phm_torch.surrogates.fdi_mlp import FDIMLP
from phm_torch.surrogates.full_signal_check import FullSignalCheck
from phm_torch.surrogates.gappy_pod import GappyPOD
from phm_torch.surrogates.ood_calibration import shape_thresholds

pytestmark = pytest.mark.torchscript  # scripts, saves or loads TorchScript on purpose

N_FULL, N_MODES = 2001, 6
NOMINAL = list(load_actuator().nominal_faults)


def damage() -> DamageModel:
    f = torch.diag(torch.tensor([5e-4] * 6 + [0.0, 3e-4], dtype=torch.float64))
    f[1, 0] = 2e-4
    return DamageModel(f.tolist(), [1e-6] * 6 + [0.0, 1e-6], 100.0, 20000.0, 50.0, NOMINAL)


@pytest.fixture(scope="module")
def pipeline() -> OnlinePipeline:
    g = torch.Generator().manual_seed(0)
    t = torch.linspace(0, 1, N_FULL, dtype=torch.float64)
    modes = torch.linalg.qr(torch.stack([torch.sin((i + 1) * 3.0 * t + i) for i in range(N_MODES)], 1))[0]
    mean = 1.0 + 0.5 * torch.sin(9 * t)
    idx = torch.linspace(0, N_FULL - 1, 24).round().long()
    gappy = GappyPOD(modes, mean, idx)
    fdi = FDIMLP(N_MODES, 10).double()
    k = torch.rand(400, 8, generator=g, dtype=torch.float64) ** 3
    k[:, 6:] = 0.5
    clf = PolynomialSVM(degree=2).fit(k, k[:, :6].amax(1) < 0.3)
    pipe = OnlinePipeline(
        gappy,
        fdi,
        clf,
        damage(),
        torch.tensor([0.02, 0.0, -0.02]),
        torch.tensor([1.0] * 6 + [0.0, 1.0]),
        N_FULL,
        residual_threshold=0.05,
    )
    pipe.modes, pipe.mean_signal = modes, mean  # for the tests
    return pipe.eval()


class ConstantFDI(torch.nn.Module):
    """An alpha -> k_hat module with the one-argument interface (no noise input)."""

    def forward(self, alpha: torch.Tensor) -> torch.Tensor:
        return torch.full((alpha.shape[0], 8), 0.01, dtype=alpha.dtype)


def test_any_alpha_to_k_module_fits_and_scripts(pipeline):
    pipe = OnlinePipeline(
        pipeline.gappy,
        ConstantFDI(),
        pipeline.classifier,
        damage(),
        torch.zeros(3),
        torch.ones(8),
        N_FULL,
        residual_threshold=0.05,
    ).eval()
    assert not pipe.noise_aware
    x = signals(pipeline, 3)
    torch.testing.assert_close(torch.jit.script(pipe)(x)[0], torch.full((3, 8), 0.01, dtype=torch.float64))


def signals(pipe, n: int, seed: int = 1) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    alpha = torch.randn(n, N_MODES, generator=g, dtype=torch.float64)
    return pipe.mean_signal + alpha @ pipe.modes.T


def test_rul_equals_torchdiffeq_propagation_with_the_same_score(pipeline):
    k = torch.tensor(
        [[0.05, 0.0, 0.02, 0.0, 0.0, 0.0, 0.5, 0.5], [0.01] * 6 + [0.5, 0.5], [0.9] + [0.0] * 5 + [0.5, 0.5]],
        dtype=torch.float64,
    )
    fast = pipeline.rul(k)
    est = RULEstimator(damage(), lambda x: pipeline.classifier(x) - pipeline.classifier.threshold, refine_iterations=14)
    det = DeterministicRUL(est)
    torch.testing.assert_close(det.direction, pipeline.direction.to(det.direction))
    for j, d in enumerate(pipeline.deltas):
        ref, _ = est.first_crossing(det.disturbed(k, float(d)))
        torch.testing.assert_close(fast[:, j], ref, rtol=0.01, atol=5.0)
    assert fast[2].eq(0).all()  # already faulty
    assert (fast[:2, 0] <= fast[:2, 1]).all() and (fast[:2, 1] <= fast[:2, 2]).all()
    # the rate band: the median propagation on a wear clock sped up by s_q
    scales = torch.tensor([1.3, 1.0, 0.8], dtype=torch.float64)
    rate = OnlinePipeline(
        pipeline.gappy,
        pipeline.fdi,
        pipeline.classifier,
        damage(),
        pipeline.deltas[1].repeat(3),
        pipeline.direction,
        N_FULL,
        residual_threshold=0.05,
        rate_scales=scales,
    ).eval()
    median, _ = est.first_crossing(det.disturbed(k, float(pipeline.deltas[1])))
    expected = (median.unsqueeze(1) / scales).clamp(max=float(rate.times[-1]))
    torch.testing.assert_close(rate.rul(k), expected[:, [0, 1, 2]], rtol=0.01, atol=5.0)


def test_full_signal_and_selected_samples_agree(pipeline):
    x = signals(pipeline, 5)
    a = pipeline(x)
    b = pipeline(x.index_select(1, pipeline.gappy.indices))
    for u, v in zip(a, b):
        torch.testing.assert_close(u, v, equal_nan=True)
    assert not a[3].any()  # in-span signals are in distribution


def test_garbage_never_gets_a_confident_rul(pipeline):
    x = signals(pipeline, 5)
    x[0] = 0.7  # flat line
    x[1, pipeline.gappy.indices[:20]] = float("nan")  # most samples missing
    x[2] = x[2].clamp(max=x[2].median())  # clipped
    x[3] = torch.randn(N_FULL, dtype=torch.float64)  # unlike anything in training
    _, _, rul, ood, _ = pipeline(x)
    assert ood[:4].all() and not ood[4]
    assert torch.isnan(rul[:4]).all() and torch.isfinite(rul[4]).all()
    with pytest.raises(Exception, match="input length"):
        pipeline(torch.zeros(1, 123, dtype=torch.float64))


def test_torchscript_export_reloads_without_phm_torch(pipeline, tmp_path):
    path = tmp_path / "online.pt"
    export_torchscript(pipeline, path)
    x = signals(pipeline, 4)
    x[1, 5] = float("nan")
    torch.save(x, tmp_path / "x.pt")
    eager = pipeline(x)
    code = textwrap.dedent(f"""
        import sys, torch
        m = torch.jit.load({str(path)!r})
        out = m(torch.load({str(tmp_path / "x.pt")!r}, weights_only=True))
        torch.save(list(out), {str(tmp_path / "out.pt")!r})
        assert torch.isnan(m.faulty_probability(out[1])).all()     # exported, NaN until calibrated
        assert torch.isnan(m.k_interval(out[0])[0]).all()
        assert not any(name.startswith('phm_torch') for name in sys.modules), 'phm_torch was imported'
    """)
    subprocess.run([sys.executable, "-c", code], check=True, cwd=tmp_path)
    loaded = torch.load(tmp_path / "out.pt", weights_only=True)
    for u, v in zip(eager, loaded):
        torch.testing.assert_close(v, u, rtol=1e-5, atol=1e-5, equal_nan=True)


def test_faulty_probability_is_nan_until_calibrated_then_the_platt_law(pipeline):
    score = torch.tensor([-1.0, 0.0, 2.0], dtype=torch.float64)
    assert torch.isnan(pipeline.faulty_probability(score)).all()
    pipe = copy.deepcopy(pipeline)
    pipe.verdict_scale.fill_(-4.0)
    pipe.verdict_offset.fill_(0.5)
    p = pipe.faulty_probability(score)
    torch.testing.assert_close(p, torch.sigmoid(-4.0 * score + 0.5))
    assert p[0] > p[1] > p[2]  # the lower the score, the likelier a fault
    torch.testing.assert_close(torch.jit.script(pipe).faulty_probability(score), p)


def test_pipeline_interval_is_nan_until_calibrated_then_by_the_estimates_class(pipeline):
    pipe = copy.deepcopy(pipeline)
    k_hat = torch.tensor(
        [
            [0.02] * 6 + [0.9, 0.5],  # k7 far from 0.5 is a phase: class 0
            [0.5, 0.02, 0.02, 0.02, 0.02, 0.02, 0.5, 0.5],
            [0.99, 0.6, 0.7, 0.0, 0.0, 0.0, 0.5, 0.95],
        ],
        dtype=torch.float64,
    )
    assert torch.isnan(torch.stack(pipe.k_interval(k_hat))).all()
    widths = torch.tensor([[0.01] * 8, [0.05] * 8, [0.1] * 8, [0.3] * 8], dtype=torch.float64)
    pipe.k_half_widths = widths.unsqueeze(0)  # one noise level
    lower, upper = pipe.k_interval(k_hat)
    torch.testing.assert_close(upper[0], (k_hat[0] + 0.01).clamp(max=1.0))
    torch.testing.assert_close(lower[1], (k_hat[1] - 0.05).clamp(min=0.0))
    torch.testing.assert_close(upper[2], (k_hat[2] + 0.3).clamp(max=1.0))  # 4 large faults: the last class
    assert float(upper[2, 0]) == 1.0 and float(lower[2, 3]) == 0.0  # clipped to [0, 1]
    scripted = torch.jit.script(pipe)
    for a, b in zip(scripted.k_interval(k_hat), (lower, upper)):
        torch.testing.assert_close(a, b)
    with pytest.raises(
        ValueError,
        match=r"online.k_half_widths must be \(n_classes, 8\) or \(n_levels, n_classes, 8\), "
        r"got \(4, 7\)",
    ):
        type(pipe)(
            pipe.gappy,
            pipe.fdi,
            pipe.classifier,
            damage(),
            pipe.deltas,
            pipe.direction,
            pipe.n_full,
            0.05,
            k_half_widths=widths[:, :7],
        )


def test_interval_widths_follow_the_records_noise_between_calibrated_levels(pipeline):
    widths = torch.stack([torch.full((4, 8), 0.01), torch.full((4, 8), 0.03), torch.full((4, 8), 0.09)])
    widths[:, 3] *= 10  # the hardest class, at every level
    pipe = type(pipeline)(
        pipeline.gappy,
        pipeline.fdi,
        pipeline.classifier,
        damage(),
        pipeline.deltas,
        pipeline.direction,
        pipeline.n_full,
        0.05,
        k_half_widths=widths.double(),
        interval_noise=torch.tensor([0.01, 0.03, 0.1]),
    )
    k_hat = torch.tensor([[0.1] * 6 + [0.5, 0.5]] * 5, dtype=torch.float64)
    noise = torch.tensor([0.0, 0.01, 0.02, 0.065, 0.5], dtype=torch.float64)
    lower, upper = pipe.k_interval(k_hat, noise)
    half = (upper - lower)[:, 0] / 2
    torch.testing.assert_close(half, torch.tensor([0.01, 0.01, 0.02, 0.06, 0.09], dtype=torch.float64))
    torch.testing.assert_close(pipe.k_interval(k_hat)[1], upper[:1].expand(5, 8))  # no noise given: level 0
    scripted = torch.jit.script(pipe)
    for a, b in zip(scripted.k_interval(k_hat, noise), (lower, upper)):
        torch.testing.assert_close(a, b)
    with pytest.raises(
        ValueError, match=r"online.interval_noise must hold 3 increasing levels, got \[0.03, 0.01, 0.1\]"
    ):
        type(pipeline)(
            pipeline.gappy,
            pipeline.fdi,
            pipeline.classifier,
            damage(),
            pipeline.deltas,
            pipeline.direction,
            pipeline.n_full,
            0.05,
            k_half_widths=widths,
            interval_noise=torch.tensor([0.03, 0.01, 0.1]),
        )


def test_pipeline_interval_class_is_the_libraries_difficulty_class(pipeline):
    """The scripted pipeline counts large faults inline; it must agree with fdi_interval.difficulty_class,
    which calibrates the widths."""
    from phm_torch.online.fdi_interval import difficulty_class

    g = torch.Generator().manual_seed(5)
    k_hat = 0.8 * torch.rand(400, 8, generator=g, dtype=torch.float64) ** 3  # mostly small: every class
    k_hat[:, 7] = 0.5 + 0.5 * (k_hat[:, 7] - 0.4)
    widths = torch.arange(4, dtype=torch.float64).view(4, 1).expand(4, 8) * 0.01 + 0.001
    pipe = copy.deepcopy(pipeline)
    pipe.k_half_widths = widths.unsqueeze(0).clone()
    _, upper = pipe.k_interval(k_hat)  # k_hat <= 0.8: upper is never clipped
    cls = torch.round(((upper - k_hat)[:, 0] - 0.001) / 0.01).long()
    assert torch.equal(cls, difficulty_class(k_hat, pipe.nominal.double(), pipe.interval_level, 4))
    assert len(set(cls.tolist())) == 4


def test_noise_level_recovers_white_noise_on_a_smooth_record_and_skips_missing_samples(pipeline):
    x = signals(pipeline, 4)
    g = torch.Generator().manual_seed(3)
    relative = torch.tensor([0.0, 0.005, 0.02, 0.05], dtype=torch.float64)
    level = x.pow(2).mean(1).sqrt()
    noisy = x + (relative * level).unsqueeze(1) * torch.randn(x.shape, generator=g, dtype=torch.float64)
    est = pipeline.noise_level(noisy)
    assert float(est[0]) < 1e-3  # the smooth record alone: ~0
    torch.testing.assert_close(est[1:], relative[1:], rtol=0.08, atol=0.0)
    holed = noisy.clone()
    holed[:, 100:160] = float("nan")
    torch.testing.assert_close(pipeline.noise_level(holed)[1:], relative[1:], rtol=0.08, atol=0.0)
    torch.testing.assert_close(torch.jit.script(pipeline).noise_level(noisy), est)
    assert torch.isnan(pipeline.calibration_noise)  # unknown until phm-evaluate sets it
    with pytest.raises(ValueError, match=r"noise_level: x must be \(B, n_full\)"):
        pipeline.noise_level(noisy[:, :24])


def test_rul_search_scores_in_blocks_with_the_same_result(pipeline):
    x = signals(pipeline, 40)
    whole = pipeline(x)
    pipe = copy.deepcopy(pipeline)
    pipe.score_block = 50  # 40 records x 3 quantiles x 17 coarse points: many blocks
    for a, b in zip(pipe(x), whole):
        torch.testing.assert_close(a, b, equal_nan=True, rtol=0, atol=0)
    for a, b in zip(torch.jit.script(pipe)(x), whole):
        torch.testing.assert_close(a, b, equal_nan=True, rtol=1e-6, atol=1e-6)


def test_rebase_moves_another_benchs_records_onto_the_training_model(pipeline, tmp_path):
    x = signals(pipeline, 3)
    assert torch.isnan(pipeline.rebase(x, pipeline.mean_signal)).all()  # no nominal record: NaN
    pipe = copy.deepcopy(pipeline)
    pipe.nominal_record.copy_(pipeline.mean_signal + 0.1)
    offset = 0.05 * torch.sin(torch.linspace(0, 30, N_FULL, dtype=torch.float64))  # what the other bench adds
    moved = pipe.rebase(x + offset, pipe.nominal_record + offset)
    torch.testing.assert_close(moved, x, rtol=0, atol=1e-12)
    torch.testing.assert_close(torch.jit.script(pipe).rebase(x + offset, pipe.nominal_record + offset), moved)
    with pytest.raises(ValueError, match="rebase: x must be"):
        pipe.rebase(x[:, :-1], pipe.nominal_record)


def test_predict_refuses_a_baseline_without_the_training_nominal_record(pipeline, compose, tmp_path):
    from phm_torch.apps.predict import predict

    export_torchscript(pipeline, tmp_path / "online.pt")
    csv = "examples/workbench_hidden_cogging.csv"
    with pytest.raises(ValueError, match="baseline: the pipeline .* holds no nominal record"):
        predict(compose("predict", [f"pipeline={tmp_path / 'online.pt'}", f"measurements={csv}", f"baseline={csv}"]))


def test_predict_warns_when_a_baseline_could_be_given_and_is_not(pipeline, compose, tmp_path, caplog):
    from phm_torch.apps.predict import predict

    pipe = copy.deepcopy(pipeline)
    pipe.nominal_record.copy_(pipeline.mean_signal)
    export_torchscript(pipe, tmp_path / "online.pt")
    zeros = torch.zeros(N_FULL, dtype=torch.float64)
    csv = write_measurement(
        tmp_path / "run.csv",
        {
            "time": torch.arange(N_FULL, dtype=torch.float64) / 20000.0,
            "command": zeros,
            "position": zeros,
            "current": pipeline.mean_signal,
        },
    )
    args = [f"pipeline={tmp_path / 'online.pt'}", f"measurements={csv}"]
    with caplog.at_level(logging.WARNING, logger="phm_torch.apps.predict"):
        metrics, _ = predict(compose("predict", args))
    assert not metrics["baseline"] and sum("no baseline" in r.getMessage() for r in caplog.records) == 1
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger="phm_torch.apps.predict"):
        metrics, _ = predict(compose("predict", [*args, f"baseline={csv}"]))
    assert metrics["baseline"] and not any("no baseline" in r.getMessage() for r in caplog.records)
    caplog.clear()
    export_torchscript(pipeline, tmp_path / "plain.pt")  # no nominal record: nothing to give
    with caplog.at_level(logging.WARNING, logger="phm_torch.apps.predict"):
        predict(compose("predict", [f"pipeline={tmp_path / 'plain.pt'}", f"measurements={csv}"]))
    assert not any("no baseline" in r.getMessage() for r in caplog.records)


def test_bundle_carries_the_nominal_record_into_the_pipeline(pipeline, tmp_path):
    from phm_torch.surrogates import POD, SurrogateBundle

    pod = POD(N_MODES)
    pod.mean_, pod.modes_ = pipeline.mean_signal, pipeline.modes
    pod.singular_values_, pod.energy_ = torch.ones(N_MODES, dtype=torch.float64), torch.ones(N_MODES) / N_MODES
    nominal = pipeline.mean_signal + 0.2
    bundle = SurrogateBundle(
        pod, pipeline.gappy.indices, pipeline.fdi, pipeline.classifier, 20000.0, 1.0, nominal_record=nominal
    )
    back = SurrogateBundle.load(bundle.save(tmp_path / "surrogates.pt"))
    assert torch.equal(back.nominal_record, nominal)
    pipe = OnlinePipeline.from_bundle(back, damage(), torch.zeros(3), torch.ones(8))
    torch.testing.assert_close(pipe.nominal_record, nominal.to(pipe.nominal_record.dtype))
    with pytest.raises(ValueError, match="nominal_record must have shape"):
        SurrogateBundle(
            pod, pipeline.gappy.indices, pipeline.fdi, pipeline.classifier, 20000.0, nominal_record=nominal[:-1]
        )


def test_full_record_check_flags_what_the_few_gappy_samples_cannot(pipeline):
    """A full record outside the POD span is flagged even when its few selected samples fit: here noise
    whose selected samples are replaced by an in-distribution record's."""
    # these few-cycle synthetic records have broad crests (1 % of samples within 0.1 % of the peak)
    check = FullSignalCheck(
        pipeline.modes, pipeline.mean_signal, stride=2, residual_threshold=0.5, plateau_threshold=0.05
    )
    good = signals(pipeline, 3)
    torch.testing.assert_close(check.residual(good), torch.zeros(3, dtype=torch.float64), rtol=0, atol=1e-6)
    g = torch.Generator().manual_seed(5)
    noise = pipeline.mean_signal + torch.randn(2, N_FULL, generator=g, dtype=torch.float64)
    assert (check.residual(noise) > 0.95).all()  # ~sqrt(1 - n_m / n) for white noise
    d = noise[0] - pipeline.mean_signal  # stride 1: the plain projection residual
    exact = (d - pipeline.modes @ (pipeline.modes.T @ d)).norm() / d.norm()
    torch.testing.assert_close(FullSignalCheck(pipeline.modes, pipeline.mean_signal, 1).residual(noise[:1])[0], exact)
    disguised = noise[:1].clone()
    disguised[0, pipeline.gappy.indices] = good[0, pipeline.gappy.indices]
    checked = OnlinePipeline(
        pipeline.gappy,
        pipeline.fdi,
        pipeline.classifier,
        damage(),
        pipeline.deltas,
        pipeline.direction,
        N_FULL,
        residual_threshold=0.05,
        full_check=check,
    ).eval()
    x = torch.cat([good, disguised])
    assert not pipeline(x)[3][3]  # the gappy residual alone is fooled
    _, _, rul, ood, _ = checked(x)
    assert ood.tolist() == [False, False, False, True] and torch.isnan(rul[3]).all()
    scripted = torch.jit.script(checked)
    for u, v in zip(checked(x), scripted(x)):
        torch.testing.assert_close(v, u, equal_nan=True)
    with pytest.raises(ValueError, match="stride"):
        FullSignalCheck(pipeline.modes, pipeline.mean_signal, stride=0)
    with pytest.raises(ValueError, match="plateau_threshold"):
        FullSignalCheck(pipeline.modes, pipeline.mean_signal, plateau_threshold=0.0)


def test_shape_statistics_flag_noise_clipping_and_crests_but_not_smooth_records():
    """Roughness: sqrt(2) for white noise, ~0 for a smooth record; plateau: the clipped share of a record."""
    n = 10001
    t = torch.linspace(0.0, 0.5, n, dtype=torch.float64)
    # a current pulse on a slow wave: a sharp peak, like the envelope current's (a broad sine crest would
    # sit on its own "plateau", as the docstring of FullSignalCheck says)
    smooth = 0.2 + 2 * torch.exp(-(((t - 0.15) / 0.02) ** 2)) + 0.3 * torch.sin(2 * math.pi * 13 * t)
    modes = torch.linalg.qr(torch.randn(n, 4, dtype=torch.float64, generator=torch.Generator().manual_seed(0)))[0]
    check = FullSignalCheck(modes, torch.zeros(n, dtype=torch.float64))
    noise = torch.randn(1, n, dtype=torch.float64, generator=torch.Generator().manual_seed(1))
    assert check.roughness(noise).item() == pytest.approx(math.sqrt(2.0), rel=0.08)  # 626 sampled pairs
    assert check.roughness(smooth[None]).item() < 0.05
    clipped = smooth.clamp(max=0.8 * float(smooth.max()))[None]
    sampled = clipped[:, check.shape_rows]
    on_top = (sampled >= sampled.max() - 1e-3 * (sampled.max() - sampled.min())).double().mean()
    assert on_top == pytest.approx(float((clipped >= clipped.max() - 1e-6).double().mean()), abs=0.02)
    torch.testing.assert_close(check.plateau(clipped)[0], on_top)
    assert check.plateau(smooth[None]).item() < 0.005 < check.plateau(clipped).item()
    x = torch.cat([smooth[None], noise, clipped, smooth[None] + 0.01 * noise])
    assert check(x).tolist() == [False, True, True, False]  # 1 % noise is a measurement, not garbage


def test_a_slow_crest_is_not_a_plateau_on_a_short_record_or_at_the_end_of_a_slow_chirp():
    """The plateau threshold never asks for fewer than three sampled points on the plateau, and phm-train raises
    it above the clean training records' own: a test command ending on a slow crest sampled at 10 kHz put 2-3
    of 313 points within 0.1 % of the range from the maximum, and 9 % of such a training set was called clipped.
    A record clipped at 70 % of its peak stays flagged (at 80 %: 97 % of them)."""
    n = 5001  # 0.5 s at 10 kHz: 313 sampled points at stride 16
    t = torch.linspace(0.0, 0.5, n, dtype=torch.float64)
    phase = 2 * math.pi * 6.0 * t**2  # 0-6 Hz over 0.5 s: a last crest a few ms broad
    g = torch.Generator().manual_seed(3)
    amplitude = 3.0 + 0.3 * torch.rand(64, 1, dtype=torch.float64, generator=g)
    offset = 2 * math.pi * torch.rand(64, 1, dtype=torch.float64, generator=g)
    records = 1.0 + amplitude * torch.sin(phase + offset) * torch.exp(-(((t - 0.48) / 0.2) ** 2))
    modes = torch.linalg.qr(torch.randn(n, 4, dtype=torch.float64, generator=torch.Generator().manual_seed(0)))[0]
    check = FullSignalCheck(modes, torch.zeros(n, dtype=torch.float64))
    assert check.plateau_threshold == pytest.approx(2.5 / 313)
    assert float(check.plateau(records).max()) > 2.5 / 313  # the physical default alone flags some
    rough, threshold = shape_thresholds(records, check, 0.999)
    assert rough == check.roughness_threshold  # smooth records: the physical default
    assert threshold > float(check.plateau(records).max())
    calibrated = FullSignalCheck(
        modes, torch.zeros(n, dtype=torch.float64), roughness_threshold=rough, plateau_threshold=threshold
    )
    assert not calibrated(records).any()
    clipped = torch.minimum(records, 0.7 * records.amax(1, keepdim=True))
    assert calibrated(clipped).all()
    clipped = torch.minimum(records, 0.8 * records.amax(1, keepdim=True))
    assert float(calibrated(clipped).double().mean()) > 0.9
    # records whose peak is sharp keep the physical default
    short = torch.linspace(0.0, 1.0, 1001, dtype=torch.float64)
    sharp = torch.exp(-(((short - 0.3) / 0.01) ** 2))[None].repeat(4, 1)
    eye = torch.eye(1001, 2, dtype=torch.float64)
    short_check = FullSignalCheck(eye, torch.zeros(1001, dtype=torch.float64))
    assert short_check.plateau_threshold == pytest.approx(2.5 / 63)  # 0.5 % would be a third of one point
    assert shape_thresholds(sharp, short_check, 0.999)[1] == short_check.plateau_threshold
    assert not short_check(sharp).any()
    with pytest.raises(ValueError, match="ood_quantile"):
        shape_thresholds(records, check, 1.5)


def test_a_coarsely_sampled_record_is_not_noise_and_white_noise_still_is():
    """phm-train raises the roughness threshold above the clean training records' own (a smooth current sampled a
    few times above its content is rough from sample to sample: the reference's heaviest fault reads 0.25 at
    20 kHz and 0.76 at 5 kHz), at most to 1.3: white noise (sqrt 2) is flagged whatever the training set."""
    n = 2001
    t = torch.arange(n, dtype=torch.float64)
    g = torch.Generator().manual_seed(4)
    fast = 0.17 + 0.02 * torch.rand(32, 1, dtype=torch.float64, generator=g)  # cycles per sample
    records = torch.sin(2 * math.pi * 0.002 * t) + 0.9 * torch.sin(2 * math.pi * fast * t)
    modes = torch.eye(n, 2, dtype=torch.float64)
    check = FullSignalCheck(modes, torch.zeros(n, dtype=torch.float64))
    roughness = check.roughness(records)
    assert 0.5 < float(roughness.min()) and float(roughness.max()) < 1.0  # valid, below the physical default
    rough, _ = shape_thresholds(records, check, 0.999)
    assert 1.0 < rough == pytest.approx(min(1.3, 1.5 * float(torch.quantile(roughness, 0.999))))
    rougher = torch.sin(2 * math.pi * 0.002 * t) + 2.0 * torch.sin(2 * math.pi * 0.2 * t)  # the same kind, 1.14
    calibrated = FullSignalCheck(modes, torch.zeros(n, dtype=torch.float64), roughness_threshold=rough)
    assert check.roughness(rougher[None]).item() > 1.0 and not calibrated(rougher[None]).item()
    noise = torch.randn(1, n, dtype=torch.float64, generator=g)
    assert calibrated.roughness(noise).item() > 1.3 and calibrated(noise).item()
    assert shape_thresholds(3.0 * noise.repeat(4, 1), check, 0.999)[0] == 1.3  # never above the cap


def test_a_short_record_is_read_at_a_finer_stride_so_its_pod_residual_still_sees_noise():
    """501 samples at every 16th are 32 rows: a 40-mode basis spans them all and the POD residual of white noise
    would be 0 (the check silently off). record_stride keeps 8 rows per mode; the reference's 10,001 samples keep
    16 (626 rows)."""
    from phm_torch.surrogates.full_signal_check import STRIDE, record_stride

    assert record_stride(10001, 22) == STRIDE and record_stride(10001, 40) == STRIDE
    assert record_stride(501, 40) == 1 and record_stride(2501, 22) == 14
    n, n_m = 501, 40
    g = torch.Generator().manual_seed(0)
    modes = torch.linalg.qr(torch.randn(n, n_m, dtype=torch.float64, generator=g))[0]
    noise = torch.randn(3, n, dtype=torch.float64, generator=g)
    zero = torch.zeros(n, dtype=torch.float64)
    assert (FullSignalCheck(modes, zero, stride=STRIDE).residual(noise) < 1e-6).all()  # blind at a stride of 16
    assert (FullSignalCheck(modes, zero).residual(noise) > 0.9).all()  # ~sqrt(1 - 40 / 501)
