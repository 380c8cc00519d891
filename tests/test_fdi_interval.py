"""Per-parameter k_hat intervals: conformal coverage per difficulty class, pooling, bad arguments (the
pipeline's method: test_online.py)."""

from __future__ import annotations

import pytest
import torch
from test_online import N_FULL, pipeline  # noqa: F401  (the fixture)

from phm_torch.online.fdi_interval import calibrate_fdi_interval, difficulty_class, interval_quality

NOMINAL = torch.tensor([0.0] * 6 + [0.5, 0.5], dtype=torch.float64)
SCALES = torch.tensor([0.01, 0.03, 0.08, 0.2], dtype=torch.float64)  # error scale of 0, 1, 2, 3+ large faults


def population(n: int, seed: int) -> tuple[torch.Tensor, torch.Tensor]:
    """True k with 0-4 large faults, and estimates whose error scale grows with their number of large
    faults (measured on the estimate, as the pipeline does)."""
    g = torch.Generator().manual_seed(seed)
    k = 0.25 * torch.rand(n, 8, generator=g, dtype=torch.float64)
    large = torch.rand(n, 8, generator=g, dtype=torch.float64) < 0.3
    k = torch.where(large, 0.45 + 0.5 * torch.rand(n, 8, generator=g, dtype=torch.float64), k)
    k[:, 6] = torch.rand(n, generator=g, dtype=torch.float64)
    k[:, 7] = 0.5 + 0.5 * (k[:, 7] - 0.5)
    cls = difficulty_class(k, NOMINAL, 0.3, 4)
    k_hat = k + SCALES[cls].unsqueeze(1) * torch.randn(n, 8, generator=g, dtype=torch.float64)
    return k_hat, k


def test_coverage_holds_in_every_difficulty_class_on_fresh_records():
    k_hat, k = population(8000, 0)
    interval = calibrate_fdi_interval(k_hat, k, NOMINAL, coverage=0.9, min_count=20)
    assert min(interval.counts) > 300 and interval.pooled_from == [0, 1, 2, 3]
    new_hat, new_k = population(40000, 1)
    cls = difficulty_class(new_hat, NOMINAL, 0.3, 4)
    w = interval.half_widths[cls]
    lower, upper = (new_hat - w).clamp(0, 1), (new_hat + w).clamp(0, 1)
    for c in range(4):
        q = interval_quality(lower[cls == c], upper[cls == c], new_k[cls == c])
        assert all(0.87 <= v <= 0.96 for v in q["coverage"]), (c, q["coverage"])
    # widths follow the error scale: ~1.645 sigma (two-sided 90 % of a normal), far narrower near nominal
    assert interval.half_widths[0, 0] == pytest.approx(1.645 * float(SCALES[0]), rel=0.2)
    assert float(interval.half_widths[3].mean()) > 8 * float(interval.half_widths[0].mean())
    # one class for all: valid on average, but over-wide near nominal and short in the hardest class
    single = calibrate_fdi_interval(k_hat, k, NOMINAL, coverage=0.9, min_count=20, n_classes=1)
    w1 = single.half_widths[0]
    hardest = interval_quality(
        (new_hat - w1).clamp(0, 1)[cls == 3], (new_hat + w1).clamp(0, 1)[cls == 3], new_k[cls == 3]
    )
    assert max(hardest["coverage"][:6]) < 0.8
    assert float(w1[:6].mean()) > 3 * float(interval.half_widths[0, :6].mean())


def test_a_small_class_is_pooled_downwards_and_widths_never_shrink_with_difficulty():
    k_hat, k = population(4000, 2)
    cls = difficulty_class(k_hat, NOMINAL, 0.3, 4)
    keep = (cls < 3) | (torch.arange(len(cls)) % 40 == 0)  # few records with 3+ large faults
    interval = calibrate_fdi_interval(k_hat[keep], k[keep], NOMINAL, coverage=0.9, min_count=50)
    assert interval.counts[3] < 50 and interval.pooled_from[3] < 3
    assert (interval.half_widths[1:] >= interval.half_widths[:-1]).all()


@pytest.mark.parametrize(
    "kwargs, message",
    [
        ({"coverage": 1.0}, r"fdi_interval.coverage must be in \(0, 1\), got 1.0"),
        ({"min_count": 0}, "fdi_interval.min_count must be an integer >= 1, got 0"),
        ({"min_count": 500}, "fdi_interval: 100 calibration records, at least min_count=500 needed"),
        ({"level": 0.0}, "fdi_interval.level must be > 0, got 0.0"),
        ({"n_classes": 0}, "fdi_interval.n_classes must be an integer >= 1, got 0"),
    ],
)
def test_bad_arguments_are_named(kwargs, message):
    k_hat, k = population(100, 3)
    args = {"coverage": 0.9, "min_count": 20, **kwargs}
    with pytest.raises(ValueError, match=message):
        calibrate_fdi_interval(k_hat, k, NOMINAL, **args)
    with pytest.raises(ValueError, match=r"must both be \(N, 8\)"):
        calibrate_fdi_interval(k_hat[:, :7], k[:, :7], NOMINAL, 0.9, 20)


@pytest.mark.parametrize(
    "override, message",
    [
        ("fdi_interval.coverage=1.0", r"fdi_interval.coverage must be in \(0, 1\), got 1.0"),
        ("fdi_interval.coverage=0", r"fdi_interval.coverage must be > 0, got 0"),
        ("fdi_interval.min_count=0", r"fdi_interval.min_count must be >= 1, got 0"),
        (
            "fdi_interval.noise_levels=[0.05,0.03]",
            r"fdi_interval.noise_levels\[1\] must exceed 0.05 \(fdi_band.noise and the levels before it, increasing\), got 0.03",
        ),
        ("fdi_interval.noise_levels=[0.005]", r"fdi_interval.noise_levels\[0\] must exceed 0.01"),
    ],
)
def test_evaluate_refuses_bad_interval_settings_before_any_work(compose, tmp_path, override, message):
    from phm_torch.apps.evaluate import evaluate_rul

    with pytest.raises(ValueError, match=message):
        evaluate_rul(compose("evaluate", [override, f"data_dir={tmp_path / 'none'}", f"out_dir={tmp_path / 'out'}"]))


def test_a_sparse_easiest_class_is_pooled_upwards():
    """A calibration set with almost no record in the easiest class (a store sampled far from nominal) pools
    that class with the next ones instead of taking a quantile of nothing."""
    k_hat, k = population(2000, 3)
    keep = difficulty_class(k_hat, NOMINAL, 0.3, 4) > 0
    keep[:3] = True  # a few easy records only
    interval = calibrate_fdi_interval(k_hat[keep], k[keep], NOMINAL, coverage=0.9, min_count=20)
    assert interval.counts[0] < 20 and torch.isfinite(interval.half_widths).all()
    assert (interval.half_widths[1:] >= interval.half_widths[:-1]).all()


def test_a_component_the_command_does_not_identify_gets_the_whole_range(pipeline):  # noqa: F811
    """phm-evaluate's interval calibration: a conformal width holds only for the calibration split's own spread
    of a component whose k_hat is the training prior, so an unidentified component's interval is [0, 1] at every
    noise level, and the others keep their calibrated widths."""
    import copy

    from phm_torch.pipelines.evaluate.calibration import fdi_intervals
    from phm_torch.pipelines.evaluate.settings import CalibrationSettings

    g = torch.Generator().manual_seed(3)
    t = torch.linspace(0, 1, N_FULL, dtype=torch.float64)
    k = torch.rand(120, 8, generator=g, dtype=torch.float64) * 0.5
    clean = pipeline.mean_signal + 0.05 * torch.sin(7 * t + 3 * k[:, :1]) * k[:, 1:2]
    with torch.no_grad():
        k_hat, _, _, ood, _ = pipeline(clean)
    settings = CalibrationSettings.from_nodes(
        {"split": "val", "noise": 0.01, "correct_median": False},
        {"prior_faulty": None},
        {"coverage": 0.9, "min_count": 20, "noise_levels": [0.03]},
        0.999,
        0.999,
    )
    widths = {}
    for unidentified in ((), (5,)):
        pipe = copy.deepcopy(pipeline)
        fdi_intervals(settings, pipe, k_hat, ood, clean, k, 0, unidentified)
        widths[unidentified] = pipe.k_half_widths
    assert widths[()].shape[0] == 2 and (widths[()][..., 5] < 1.0).all()
    assert (widths[(5,)][..., 5] == 1.0).all()
    keep = [j for j in range(8) if j != 5]
    torch.testing.assert_close(widths[(5,)][..., keep], widths[()][..., keep])
    lower, upper = pipe.k_interval(k_hat, torch.full((k_hat.shape[0],), 0.01, dtype=k_hat.dtype))
    assert (lower[:, 5] == 0).all() and (upper[:, 5] == 1).all()
