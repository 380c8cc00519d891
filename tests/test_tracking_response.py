"""The FDI's response near nominal (phm_torch.tracking.response): the fitted curve, its inverse, its JSON and its
provenance check, and what it does for the tracker: a compressive FDI reads the wear rate low and the RUL long,
and inverting its response removes that bias."""

from __future__ import annotations

import itertools
import json

import numpy as np
import pytest
import torch
from test_tracking import NOMINAL, law, pipeline, scale_of, tracker, truth_path  # noqa: F401 (fixtures)

from phm_torch.faults import FAULT_NAMES
from phm_torch.tracking.response import FDIResponse, fit_response, pairs_from_track, probe_k_hat


def compressive(k: np.ndarray) -> np.ndarray:
    """A response like the pretrained FDI's on backlash: small damages read at 0.55 of their size up to 0.02,
    slope 1 beyond; the eccentricity phase (k7) not identified (its estimate does not follow k)."""
    out = np.where(k < 0.02, 0.55 * k, 0.011 + (k - 0.02))
    out[:, 6] = 0.5
    out[:, 7] = k[:, 7]
    return out


def synthetic_pairs(n: int = 4000, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    k = rng.uniform(0.0, 0.1, (n, 8)) ** 1.5 * 3.0
    k[:, 6] = rng.uniform(0, 1, n)
    k[:, 7] = 0.5 + rng.normal(0, 0.01, n)
    return k, compressive(k) + rng.normal(0, 0.002, (n, 8))


def test_the_fitted_response_inverts_a_compressive_fdi_and_leaves_an_unidentified_component_alone():
    k, k_hat = synthetic_pairs()
    r = fit_response(k, k_hat, n_bins=12)
    assert "eccentricity_phase" not in r.corrected and "backlash" in r.corrected
    grid = np.linspace(0.003, 0.08, 30)
    probe = np.tile(grid[:, None], (1, 8))
    probe[:, 6], probe[:, 7] = 0.3, 0.5
    back = r.invert(torch.from_numpy(compressive(probe))).numpy()
    # within the bins' resolution of the true k; the raw estimate was off by up to 0.009
    assert np.abs(back[:, :6] - probe[:, :6]).max() < 2.5e-3
    assert np.abs(compressive(probe)[:, :6] - probe[:, :6]).max() > 8e-3
    assert back[0, 6] == pytest.approx(0.5)  # left as measured
    # beyond the knots: slope 1, clamped to [0, 1]
    edge = torch.full((1, 8), 0.99, dtype=torch.float64)
    assert float(r.invert(edge)[0, 0]) == pytest.approx(0.99 + r.knots_true[0][-1] - r.knots_hat[0][-1])
    low, high = torch.full((1, 8), 0.0, dtype=torch.float64), torch.full((1, 8), 0.05, dtype=torch.float64)
    kc, lo, hi = r.correct(torch.full((1, 8), 0.02, dtype=torch.float64), low, high)
    assert float(lo.min()) >= 0.0 and torch.allclose(hi - kc, high - 0.02)


def test_the_response_is_non_decreasing_and_roundtrips_through_json(tmp_path):
    k, k_hat = synthetic_pairs()
    k_hat[:, 1] += 0.004 * np.sin(k[:, 1] * 400)  # a wiggle: the isotonic fit pools it
    r = fit_response(k, k_hat, pipeline={"probe_k_hat": [0.0] * 8, "source": "synthetic"})
    for kh in r.knots_hat:
        assert all(b > a for a, b in itertools.pairwise(kh))
    path = tmp_path / "r.json"
    r.save(path)
    again = FDIResponse.load(path)
    assert again == r
    data = json.loads(path.read_text())
    data["format"] = "something else"
    path.write_text(json.dumps(data))
    with pytest.raises(ValueError, match="not a phm_torch.fdi_response/1 file"):
        FDIResponse.load(path)


def test_bad_fits_and_knots_are_refused():
    k, k_hat = synthetic_pairs(100)
    with pytest.raises(ValueError, match="too few"):
        fit_response(k, k_hat, n_bins=10, min_count=20)
    with pytest.raises(ValueError, match=r"must both be \(N, 8\)"):
        fit_response(k[:, :7], k_hat[:, :7])
    with pytest.raises(ValueError, match="n_bins must be an integer >= 2"):
        fit_response(k, k_hat, n_bins=1)
    knots = [()] * 8
    bad = list(knots)
    bad[2] = (0.0, 0.01)
    with pytest.raises(ValueError, match="short_a.*equally many"):
        FDIResponse(tuple(bad), tuple(knots))
    with pytest.raises(ValueError, match="strictly increasing"):
        FDIResponse(tuple(bad), tuple([()] * 2 + [(0.01, 0.0)] + [()] * 5))


def test_a_response_is_refused_for_another_pipeline(pipeline):  # noqa: F811
    k, k_hat = synthetic_pairs()
    mine = fit_response(k, k_hat, pipeline={"probe_k_hat": probe_k_hat(pipeline), "source": "mine"})
    mine.check_for(pipeline, "this pipeline")
    other = fit_response(k, k_hat, pipeline={"probe_k_hat": [v + 0.01 for v in probe_k_hat(pipeline)]})
    with pytest.raises(ValueError, match="fitted for another pipeline.*differs by 0.01"):
        other.check_for(pipeline, "this pipeline")
    with pytest.raises(ValueError, match="records no probe_k_hat"):
        fit_response(k, k_hat).check_for(pipeline, "this pipeline")


def test_pairs_come_from_the_in_distribution_inspections_of_a_track():
    truth = {"actuators": {"A": {"inspections": [{"hours": h, "k_true": [h / 1000] * 8} for h in (0.0, 200.0, 400.0)]}}}
    names = list(FAULT_NAMES)
    track = {
        "actuators": {
            "A": {
                "inspections": [
                    {"hours": h, "k_hat": dict(zip(names, [h / 900] * 8)), "out_of_distribution": h == 200.0}
                    for h in (0.0, 200.0, 400.0)
                ]
            }
        }
    }
    k_true, k_hat = pairs_from_track(track, truth)
    assert k_true.shape == (2, 8) and k_hat[1, 0] == pytest.approx(400 / 900)


def test_inverting_a_compressive_response_removes_the_trackers_long_rul(pipeline, law):  # noqa: F811
    """Histories read through an FDI that reads every damage at 0.7 of its size: the filter's k is low and its RUL
    long; with the fitted response inverted k is read right and the RUL shortens by the level's share."""
    rng = np.random.default_rng(1)
    k_fit = rng.uniform(0.0, 0.5, (6000, 8))
    k_fit[:, 6:] = 0.5
    response = fit_response(k_fit, 0.7 * k_fit + rng.normal(0, 0.002, k_fit.shape), n_bins=16)
    assert response.corrected == list(FAULT_NAMES[:6])
    k = truth_path(law, [0.05, 0.0, 0.0, 0.0, 0.0, 0.05] + NOMINAL[6:], 1.5, 8)
    g = torch.Generator().manual_seed(0)
    noise = 0.002 * torch.randn(k.shape, generator=g, dtype=torch.float64)
    posts = {}
    for corrected in (False, True):
        tr = tracker(pipeline, law)
        tr.response = response if corrected else None
        for i in range(k.shape[0]):
            read = (0.7 * k[i : i + 1] + noise[i : i + 1]).clamp(0, 1)
            read[:, 6:] = k[i : i + 1, 6:]
            width = scale_of(read, 0.004)
            lo, hi = read - 1.645 * width, read + 1.645 * width
            if tr.response is not None:
                read, lo, hi = tr.response.correct(read, lo, hi)
            posts[corrected] = tr.update(
                ["A"], torch.tensor([200.0 * i]), read, (hi - read) / 1.645, torch.tensor([True])
            )
    true_k = k[-1, [0, 5]]
    assert torch.allclose(posts[False].k_mean[0, [0, 5]], 0.7 * true_k, rtol=0.08)
    assert torch.allclose(posts[True].k_mean[0, [0, 5]], true_k, rtol=0.05)
    rul_raw, rul_corrected = float(posts[False].rul[0, 1]), float(posts[True].rul[0, 1])
    # exponential growth at s F = 7.5e-4 / h: a level 0.7 of the truth is ln(1 / 0.7) / 7.5e-4 = 476 h further away
    assert rul_raw - rul_corrected == pytest.approx(476.0, rel=0.35)


def test_companion_files_follow_one_rule(pipeline, tmp_path):  # noqa: F811
    from phm_torch.tracking.companions import companion

    model_path = tmp_path / "online.pt"
    assert companion("response", "auto", model_path, pipeline) is None  # none beside: tracked without
    assert companion("response", None, model_path, pipeline) is None
    k, k_hat = synthetic_pairs()
    fit_response(k, k_hat, pipeline={"probe_k_hat": probe_k_hat(pipeline)}).save(tmp_path / "online.fdi_response.json")
    assert isinstance(companion("response", "auto", model_path, pipeline), FDIResponse)
    with pytest.raises(ValueError, match="near_nominal: no such file"):
        companion("near_nominal", str(tmp_path / "nope.pt"), model_path, pipeline)
    with pytest.raises(ValueError, match="unknown kind 'other'"):
        companion("other", "auto", model_path, pipeline)
