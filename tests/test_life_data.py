"""The wear-rate scale of the damage law and the run-to-failure ``life`` split: clock-change identity,
Monte Carlo spread vs rate_scale_sigma, analytic end of life, inspection schedule, noise, resume, bad input."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
import torch

from phm_torch.apps.generate import fingerprint
from phm_torch.command import Chirp
from phm_torch.data import life as life_split
from phm_torch.data import life_files
from phm_torch.data.generation import seed_streams
from phm_torch.io import read_measurement
from phm_torch.params import load_actuator
from phm_torch.prognostics import DamageModel, DeterministicRUL, RULEstimator

LAM = 5e-4  # 1/h
THR = 0.05  # damage at which the analytic score says faulty
PARAMS = load_actuator()
NOMINAL = list(PARAMS.nominal_faults)
Z95 = 1.6448536269514722


def diagonal(noise: float = 0.0, sigma: float = 0.0, horizon: float = 20000.0) -> DamageModel:
    f = torch.diag(torch.tensor([LAM] * 6 + [0.0, LAM], dtype=torch.float64))
    return DamageModel(f.tolist(), [noise] * 6 + [0.0, noise], 250.0, horizon, 50.0, NOMINAL, rate_scale_sigma=sigma)


def damage_of(k: torch.Tensor) -> torch.Tensor:
    """Largest damage of (N, 8) vectors: k1..k6 and |k8 - nominal| (k7 is a phase)."""
    return torch.cat([k[:, :6], (k[:, 7:] - NOMINAL[7]).abs()], dim=1).amax(1)


def score(k: torch.Tensor) -> torch.Tensor:
    return THR - damage_of(k)


# ---- the rate scale in the damage law ------------------------------------------------------------------
def test_a_rate_scale_is_a_clock_change():
    """dk/dt = s F dk + eps: noise-free, k(t; s) = k(s t; s = 1); with constant eps the exact solution is
    A(s t) dk + B(s t) eps / s (the propagators of s = 1)."""
    d = DamageModel(
        torch.tensor(
            [[6e-4, 2e-4, 0, 0, 0, 2e-4, 0, 0]] + [[0.0] * 8] * 5 + [[0.0] * 8] + [[0.0] * 7 + [3e-4]]
        ).tolist(),
        [0.0] * 8,
        250.0,
        20000.0,
        50.0,
        NOMINAL,
        rate_scale_sigma=0.35,
    )
    k0 = torch.tensor([[0.02, 0.01, 0.0, 0.0, 0.0, 0.03, 0.4, 0.52]] * 3, dtype=torch.float64)
    s = torch.tensor([0.6, 1.0, 1.7], dtype=torch.float64)
    t = d.grid[:81]  # 0 .. 4,000 h
    traj = d.integrate(k0, t=t, scale=s)  # (T, 3, 8)
    dk = (k0[0] - d.nominal).unsqueeze(-1)
    for i in range(3):
        a, _ = d.transitions(s[i] * t)
        torch.testing.assert_close(
            traj[:, i], d.nominal + (a @ dk).squeeze(-1), rtol=1e-6, atol=1e-9
        )  # RK4 truncation at s F h <= 0.07
    torch.testing.assert_close(traj[:, 1], d.integrate(k0[:1], t=t)[:, 0])  # s = 1: the old law
    eps = torch.full((3, 100, 8), 2e-6, dtype=torch.float64)
    eps[:, :, 6] = 0
    noisy = d.integrate(k0, eps, t=t, scale=s)
    for i in range(3):
        a, b = d.transitions(s[i] * t)
        exact = d.nominal + (a @ dk).squeeze(-1) + (b @ eps[i, 0]) / s[i]
        torch.testing.assert_close(noisy[:, i], exact, rtol=1e-6, atol=1e-9)  # RK4 truncation at s F h <= 0.07


def test_rate_scale_draws_are_lognormal_and_sigma_zero_draws_nothing():
    g = torch.Generator().manual_seed(0)
    s = diagonal(sigma=0.35).sample_rate_scale(20000, g)
    assert float(s.log().mean()) == pytest.approx(0.0, abs=0.01)
    assert float(s.log().std()) == pytest.approx(0.35, rel=0.02)
    g0 = torch.Generator().manual_seed(5)
    state = g0.get_state()
    assert torch.equal(diagonal().sample_rate_scale(7, g0), torch.ones(7, dtype=torch.float64))
    assert torch.equal(g0.get_state(), state)  # the datasheet's law keeps its random streams


def test_monte_carlo_rul_spread_grows_with_the_rate_scale_sigma():
    """Noise-free the RUL of a run is RUL_1 / s, so the 95 %/50 % quantile ratio is exp(1.645 sigma); with
    eps as well the spread grows monotonically with sigma. The calibrated rate band follows (its s_5 is
    that ratio) since it is calibrated on the Monte Carlo quantiles."""
    k0 = torch.tensor([[0.02, 0.0, 0.0, 0.0, 0.0, 0.0, 0.5, 0.5]], dtype=torch.float64)
    rul1 = math.log(THR / 0.02) / LAM  # 1,833 h; the slowest 5 % run fails by ~3,300 h
    est = RULEstimator(diagonal(sigma=0.35, horizon=5000.0), score, n_samples=1500, refine_iterations=8)
    q = est.estimate(k0, torch.Generator().manual_seed(1)).empirical[0]
    assert float(q[1]) == pytest.approx(rul1, rel=0.03)
    assert float(q[2] / q[1]) == pytest.approx(math.exp(Z95 * 0.35), rel=0.04)
    assert float(q[1] / q[0]) == pytest.approx(math.exp(Z95 * 0.35), rel=0.04)
    widths = []
    for sigma in (0.0, 0.15, 0.35, 0.6):
        est = RULEstimator(diagonal(noise=2e-6, sigma=sigma, horizon=6000.0), score, n_samples=300, refine_iterations=6)
        q = est.estimate(k0, torch.Generator().manual_seed(2)).empirical[0]
        widths.append(float((q[2] - q[0]) / q[1]))
    assert widths == sorted(widths) and widths[-1] > 3 * widths[0]
    k = torch.tensor([[0.02 + 0.002 * i] + [0.0] * 5 + [0.5, 0.5] for i in range(4)], dtype=torch.float64)
    det = DeterministicRUL(
        RULEstimator(diagonal(sigma=0.35, horizon=5000.0), score, n_samples=800, refine_iterations=6), "rate"
    )
    det.calibrate(k, torch.Generator().manual_seed(3), iterations=16)
    assert float(det.scales_[0]) == pytest.approx(math.exp(Z95 * 0.35), rel=0.05)
    assert float(det.scales_[2]) == pytest.approx(math.exp(-Z95 * 0.35), rel=0.05)


@pytest.mark.parametrize("value", [-0.1, float("nan"), 3.0, "0.3", True])
def test_bad_rate_scale_sigma(value):
    with pytest.raises(ValueError, match=r"damage\.rate_scale_sigma .*" + repr(value)[:3]):
        diagonal(sigma=value)


# ---- the life split --------------------------------------------------------------------------------------
def lf_simulate(duration: float = 0.01):
    """The LF simulator on a 10 ms chirp (201 samples): the records' plumbing at test cost."""
    return life_split.simulator(PARAMS, "lf", None, {}, False, Chirp(duration=duration), duration)


def make_generator(n: int = 3, sigma: float = 0.35, noise: float = 0.0, **life_kw) -> life_split.LifeGenerator:
    spec = life_split.LifeSpec(n_actuators=n, **({"initial_damage": 0.02, "batch": 8, "compile": False} | life_kw))
    return life_split.LifeGenerator(
        spec,
        diagonal(noise=noise, sigma=sigma),
        lambda k: score(k) > 0,
        lf_simulate(),
        seed_streams(0)["life"],
        NOMINAL,
        uniform=[6],
    )


def analytic_eol(k0: list[float], s: float) -> float:
    """Noise-free diagonal law: every damage grows as dk exp(s LAM t); faulty once the largest reaches THR."""
    return math.log(THR / float(damage_of(torch.tensor([k0]))[0])) / (s * LAM)


def test_life_split_schedule_truth_and_records(tmp_path):
    gen = make_generator(noise=0.0)
    metrics = life_files.generate_life(tmp_path, gen, {"k": 1}, {"every_hours": 200.0}, progress=False)
    assert metrics["computed"] == 3 and metrics["censored"] == 0
    truth = json.loads((tmp_path / "truth.json").read_text())
    assert list(truth["actuators"]) == ["A000", "A001", "A002"] and truth["every_hours"] == 200.0
    index = (tmp_path / "index.csv").read_text().splitlines()
    assert index[0] == "actuator,hours,file"
    assert len(index) - 1 == sum(len(a["inspections"]) for a in truth["actuators"].values())
    scales = []
    for name, a in truth["actuators"].items():
        hours = [i["hours"] for i in a["inspections"]]
        assert hours == [200.0 * j for j in range(len(hours))]  # every 200 h from 0
        eol, healthy = a["eol_hours"], [i["healthy"] for i in a["inspections"]]
        # the analytic crossing (resolution: 50 h / 16^2), phi_a consistent with it at every inspection
        assert eol == pytest.approx(analytic_eol(a["k0"], a["rate_scale"]), abs=0.25)
        assert healthy == [h < eol for h in hours]
        first = healthy.index(False)
        assert hours[first - 1] < eol <= hours[first]  # between last healthy and first faulty
        assert sum(h >= eol for h in hours) == 2  # after_eol inspections at/after it
        for i in a["inspections"]:
            assert i["rul_true"] == pytest.approx(eol - i["hours"])
            assert (damage_of(torch.tensor([i["k_true"]])) < THR).item() == i["healthy"]
            assert i["file"].startswith(name + "/")
        k0 = torch.tensor([a["k0"]])
        assert float(damage_of(k0)[0]) <= 0.02 and score(k0).item() > 0  # small, healthy start
        torch.testing.assert_close(torch.tensor(a["inspections"][0]["k_true"]), k0[0], rtol=0, atol=1e-12)
        scales.append(a["rate_scale"])
    assert len(set(scales)) == 3
    rec = read_measurement(
        tmp_path / truth["actuators"]["A001"]["inspections"][2]["file"], expected_rate=PARAMS.sample_rate
    )
    assert len(rec) == 201


def test_life_records_carry_the_relative_current_noise(tmp_path):
    gen = make_generator(n=1, noise=0.0)
    gen = life_split.LifeGenerator(
        life_split.LifeSpec(n_actuators=1, initial_damage=0.02, batch=4, compile=False, noise=0.05),
        gen.damage,
        gen.assess_fn,
        gen.simulate,
        gen.stream,
        NOMINAL,
        uniform=[6],
    )
    life_files.generate_life(tmp_path, gen, {"k": 1}, {}, progress=False)
    a = json.loads((tmp_path / "truth.json").read_text())["actuators"]["A000"]
    i = a["inspections"][-1]
    rec = read_measurement(tmp_path / i["file"])
    _, clean = gen.simulate(torch.tensor([i["k_true"]], dtype=torch.float64))
    cur = clean["current"][0].double().numpy()
    rms = float(np.sqrt((cur**2).mean()))
    assert float(np.std(rec.current - cur)) == pytest.approx(0.05 * rms, rel=0.15)
    np.testing.assert_allclose(rec.position, clean["position"][0].double().numpy(), rtol=0, atol=1e-7)


def test_life_split_resumes_per_actuator_and_is_deterministic(tmp_path):
    life_files.generate_life(tmp_path / "a", make_generator(n=2), {"k": 1}, {}, progress=False)
    part = (tmp_path / "a" / "A001" / "part.json").read_text()
    more = life_files.generate_life(tmp_path / "a", make_generator(n=3), {"k": 1}, {}, progress=False)
    assert (more["computed"], more["reused"]) == (1, 2)
    assert (tmp_path / "a" / "A001" / "part.json").read_text() == part  # untouched
    (tmp_path / "a" / "A001" / "part.json").unlink()  # interrupted actuator
    again = life_files.generate_life(tmp_path / "a", make_generator(n=3), {"k": 1}, {}, progress=False)
    assert (again["computed"], again["reused"]) == (1, 2)
    assert (tmp_path / "a" / "A001" / "part.json").read_text() == part  # the same history again
    fresh = life_files.generate_life(tmp_path / "b", make_generator(n=3), {"k": 1}, {}, progress=False)
    assert fresh["computed"] == 3
    assert (tmp_path / "b" / "truth.json").read_text() == (tmp_path / "a" / "truth.json").read_text()
    with pytest.raises(ValueError, match="different settings"):
        life_files.generate_life(tmp_path / "a", make_generator(n=3), {"k": 2}, {}, progress=False)
    redo = life_files.generate_life(tmp_path / "a", make_generator(n=3), {"k": 2}, {}, overwrite=True, progress=False)
    assert redo["computed"] == 3


def test_censored_history_at_the_inspection_cap(tmp_path):
    """A life longer than max_inspections is kept whole, its end of life unknown (null, censored)."""
    gen = make_generator(n=1, sigma=0.0, max_inspections=3, after_eol=1)
    life_files.generate_life(tmp_path, gen, {"k": 1}, {}, progress=False)
    a = json.loads((tmp_path / "truth.json").read_text())["actuators"]["A000"]
    assert a["eol_hours"] is None and a["censored"] and len(a["inspections"]) == 3
    assert all(i["rul_true"] is None and i["healthy"] for i in a["inspections"])


@pytest.mark.parametrize(
    "field,value",
    [
        ("n_actuators", -1),
        ("every", 0.0),
        ("every", float("inf")),
        ("initial_damage", 0.0),
        ("initial_damage", 1.5),
        ("after_eol", 0),
        ("noise", -0.01),
        ("max_inspections", 1),
        ("batch", 0),
        ("compile", "yes"),
        ("n_actuators", 2.5),
    ],
)
def test_bad_life_settings(field, value):
    with pytest.raises(ValueError, match=rf"dataset\.life\.{field} .*{str(value)[:3]}"):
        life_split.LifeSpec(**{field: value})


def test_bad_life_settings_against_the_damage_grid_and_unknown_keys():
    with pytest.raises(ValueError, match=r"dataset\.life\.every \(120.0\) must be a multiple of damage\.step_hours"):
        make_generator(every=120.0)
    with pytest.raises(ValueError, match=r"dataset\.life: unknown setting\(s\) \['evry'\]"):
        life_split.LifeSpec.of({"evry": 100})
    with pytest.raises(ValueError, match=r"dataset\.life\.after_eol \(5\) must be below"):
        life_split.LifeSpec(after_eol=5, max_inspections=5)


def test_life_settings_are_not_in_the_store_fingerprint(compose):
    """Adding a life split to a finished store must not invalidate it."""
    base = compose("generate")
    with_life = compose("generate", ["dataset.life.n_actuators=40", "dataset.life.every=100"])
    assert fingerprint(base)[0] == fingerprint(with_life)[0]
    assert fingerprint(base)[0] != fingerprint(compose("generate", ["dataset.n_train=49"]))[0]
    assert "life" not in fingerprint(base)[1]["dataset"]
