"""Life tracker (phm_torch.tracking): the filter's physics and numbers on a small synthetic pipeline, driven
by synthetic k_hat (no records): propagation, process noise, convergence of k and s, band narrowing, RUL
against the pipeline's own propagation, censoring, OOD, maintenance, batch independence."""

from __future__ import annotations

import math

import pytest
import torch

from phm_torch.online import OnlinePipeline
from phm_torch.params import load_actuator
from phm_torch.prognostics import DamageModel
from phm_torch.surrogates.classifiers.polynomial_svm import PolynomialSVM
from phm_torch.surrogates.fdi_mlp import FDIMLP
from phm_torch.surrogates.gappy_pod import GappyPOD
from phm_torch.tracking import DamageLaw, ParticleRUL, Tracker, TrackerSettings
from phm_torch.tracking.fleet import censor
from phm_torch.tracking.particle_rul import HUGE

N_FULL, N_MODES = 2001, 6
NOMINAL = list(load_actuator().nominal_faults)
HALF_WIDTH = 0.02  # calibrated 90 % half-width of the synthetic pipeline's k_hat (k7: 0.4)


def damage_config() -> dict:
    f = torch.diag(torch.tensor([5e-4] * 6 + [0.0, 3e-4], dtype=torch.float64))
    f[1, 0] = 2e-4
    return {
        "rate": f.tolist(),
        "noise_std": [1e-6] * 6 + [0.0, 1e-6],
        "noise_correlation_hours": 100.0,
        "horizon_hours": 20000.0,
        "step_hours": 50.0,
        "rate_scale_sigma": 0.35,
    }


def make_pipeline(calibrated: bool = True) -> OnlinePipeline:
    g = torch.Generator().manual_seed(0)
    t = torch.linspace(0, 1, N_FULL, dtype=torch.float64)
    modes = torch.linalg.qr(torch.stack([torch.sin((i + 1) * 3.0 * t + i) for i in range(N_MODES)], 1))[0]
    mean = 1.0 + 0.5 * torch.sin(9 * t)
    gappy = GappyPOD(modes, mean, torch.linspace(0, N_FULL - 1, 24).round().long())
    torch.manual_seed(0)
    fdi = FDIMLP(N_MODES, 10).double()
    k = torch.rand(400, 8, generator=g, dtype=torch.float64) ** 3
    k[:, 6:] = 0.5
    clf = PolynomialSVM(degree=2).fit(k, k[:, :6].amax(1) < 0.3)
    cfg = {key: v for key, v in damage_config().items() if key != "rate_scale_sigma"}
    widths = torch.full((4, 8), HALF_WIDTH, dtype=torch.float64)
    widths[:, 6] = 0.4
    pipe = OnlinePipeline(
        gappy,
        fdi,
        clf,
        DamageModel(**cfg, nominal=NOMINAL),
        torch.zeros(3),
        torch.tensor([1.0] * 6 + [0.0, 1.0]),
        N_FULL,
        residual_threshold=0.05,
        k_half_widths=widths if calibrated else None,
    )
    pipe.modes, pipe.mean_signal = modes, mean
    return pipe.eval()


@pytest.fixture(scope="module")
def pipeline() -> OnlinePipeline:
    return make_pipeline()


@pytest.fixture(scope="module")
def law(pipeline) -> DamageLaw:
    return DamageLaw.from_config(damage_config(), pipeline, "test")


def tracker(pipeline, law, **kw) -> Tracker:
    settings = TrackerSettings(**{"n_particles": 256, "rul_particles": 64, **kw})
    return Tracker(law, ParticleRUL(pipeline, law, settings.max_rate_scale, settings.bisections), settings)


def truth_path(law: DamageLaw, k_start: list[float], s: float, n: int, every: float = 200.0) -> torch.Tensor:
    """Noise-free k (n, 8) at 0, every, 2 every, ... for rate scale s."""
    dk = torch.tensor(k_start, dtype=torch.float64) - law.nominal
    out = [law.nominal + law.propagate(dk.unsqueeze(0), torch.tensor([s * i * every]))[0] for i in range(n)]
    return torch.stack(out)


def filter_state(seed: int, level: float, jitter: float) -> tuple[torch.Tensor, ...]:
    """A random Kalman state of 2 actuators x 3 particles: means (2, 3, 8) around ``level``, covariances (2, 3, 8, 8)
    with ``jitter`` on the diagonal, readings k_hat (2, 8) around it and their error scales (2, 8) of 0.01."""
    g = torch.Generator().manual_seed(seed)
    a = torch.randn(2, 3, 8, 8, generator=g, dtype=torch.float64)
    c = a @ a.transpose(-1, -2) * 1e-4 + jitter * torch.eye(8, dtype=torch.float64)
    m = level + 0.05 * torch.randn(2, 3, 8, generator=g, dtype=torch.float64)
    k_hat = level + 0.05 * torch.randn(2, 8, generator=g, dtype=torch.float64)
    return m, c, k_hat, torch.full((2, 8), 0.01, dtype=torch.float64)


def scale_of(k: torch.Tensor, width: float = HALF_WIDTH) -> torch.Tensor:
    s = torch.full_like(k, width / 2.132)
    s[..., 6] = 0.4 / 2.132
    return s


def test_propagation_is_the_matrix_exponential_of_s_f_dt(law):
    dk = torch.rand(5, 8, dtype=torch.float64)
    tau = torch.tensor([0.0, 30.0, 400.0, 5000.0, 60000.0], dtype=torch.float64)
    exact = torch.stack([torch.linalg.matrix_exp(law.rate * t) @ v for t, v in zip(tau, dk)])
    torch.testing.assert_close(law.propagate(dk, tau), exact, rtol=1e-10, atol=1e-12)


@pytest.mark.parametrize("dt", [40.0, 100.0, 700.0])
def test_process_noise_std_is_that_of_block_constant_rates_with_a_random_phase(law, dt):
    g = torch.Generator().manual_seed(1)
    n, tc = 40000, law.noise_correlation_hours
    phase = torch.rand(n, generator=g, dtype=torch.float64) * tc  # where the first block ends
    blocks = math.ceil(dt / tc) + 2
    eps = torch.randn(n, blocks, generator=g, dtype=torch.float64)
    edges = torch.cat(
        [
            torch.zeros(n, 1, dtype=torch.float64),
            phase.unsqueeze(1) + tc * torch.arange(blocks - 1, dtype=torch.float64),
        ],
        1,
    ).clamp(max=dt)
    lengths = torch.diff(torch.cat([edges, torch.full((n, 1), dt, dtype=torch.float64)], 1), dim=1)
    integral = (eps * lengths).sum(1)  # unit std per block
    expected = float(law.noise_std_over(torch.tensor([dt]))[0, 0]) / float(law.noise_std[0])
    assert abs(float(integral.std()) / expected - 1.0) < 0.02


def test_exact_measurements_converge_to_the_true_k_and_s(pipeline, law):
    k = truth_path(law, [0.02, 0.01, 0.0, 0.0, 0.0, 0.02] + NOMINAL[6:], 1.6, 15)
    tr = tracker(pipeline, law)
    for i in range(k.shape[0]):
        post = tr.update(
            ["A"], torch.tensor([200.0 * i]), k[i : i + 1], scale_of(k[i : i + 1], 0.002), torch.tensor([True])
        )
    assert float((post.k_mean[0] - k[-1])[[0, 1, 5]].abs().max()) < 0.005
    assert abs(float(post.rate_scale[0, 1]) / 1.6 - 1.0) < 0.05


def run_noisy(pipeline, law, s_true: float, n: int, seed: int = 0) -> list:
    g = torch.Generator().manual_seed(seed)
    k = truth_path(law, [0.05, 0.0, 0.0, 0.0, 0.0, 0.01] + NOMINAL[6:], s_true, n)
    tr = tracker(pipeline, law, seed=seed)
    out = []
    for i in range(n):
        k_hat = (k[i] + HALF_WIDTH / 1.645 * torch.randn(8, generator=g, dtype=torch.float64)).clamp(0, 1)
        k_hat[6] = k[i, 6]
        out.append(
            tr.update(
                ["A"], torch.tensor([200.0 * i]), k_hat.unsqueeze(0), scale_of(k_hat.unsqueeze(0)), torch.tensor([True])
            )
        )
    return out


def test_an_actuator_wearing_twice_as_fast_as_the_fleet_moves_its_rate_scale_toward_2(pipeline, law):
    runs = [run_noisy(pipeline, law, 2.0, 12, seed) for seed in range(4)]
    first = torch.stack([posts[0].rate_scale[0, 1] for posts in runs])
    last = torch.stack([posts[-1].rate_scale[0, 1] for posts in runs])
    assert float((first - 1.0).abs().max()) < 0.1  # the fleet prior: median 1
    assert float(last.median()) > 1.6, last  # 2.4 h of wear per 200 h at 12 inspections


def test_the_rul_band_narrows_with_more_inspections(pipeline, law):
    posts = run_noisy(pipeline, law, 1.0, 14)
    width = [float((p.rul[0, 2] - p.rul[0, 0]) / p.rul[0, 1]) for p in posts]
    assert width[-1] < 0.5 * width[1], width


def test_particle_rul_is_the_pipelines_propagation_on_a_wear_clock(pipeline, law):
    rul = ParticleRUL(pipeline, law, bisections=8)
    k = torch.tensor([[0.05, 0.0, 0.02, 0.0, 0.0, 0.0, 0.5, 0.5], [0.1] * 6 + [0.5, 0.5]], dtype=torch.float64)
    with torch.no_grad():
        reference = pipeline.rul(k)[:, 1]  # zero deltas: the noise-free propagation, s = 1
    tau = rul.wear_clock_crossing(k, law.horizon_hours)
    torch.testing.assert_close(tau, reference, rtol=0.01, atol=5.0)
    q, censored, _ = rul(k.unsqueeze(1).expand(2, 4, 8), torch.full((2, 4), 2.0, dtype=torch.float64))
    torch.testing.assert_close(q[:, 1], reference / 2.0, rtol=0.01, atol=5.0)  # noise-free RUL = RUL_1 / s
    assert not censored.any()


def test_rul_bounds_at_the_horizon_are_censored_and_a_faulty_verdict_has_no_life_left(pipeline, law):
    tr = tracker(pipeline, law)
    nominal = torch.tensor([NOMINAL], dtype=torch.float64)  # no damage: the law never moves it
    q, censored, _ = tr.rul_model(nominal.expand(1, 4, 8).unsqueeze(0)[0], torch.ones(1, 4, dtype=torch.float64))
    assert censored.all() and torch.isnan(q).all()
    # a barely damaged actuator: its slow particles outlive the horizon, its fast ones do not
    post = tr.update(["A"], torch.tensor([0.0]), nominal, scale_of(nominal, 1e-4), torch.tensor([True]))
    assert post.censored[0].tolist() == [False, False, True] and torch.isnan(post.rul[0, 2])
    assert 0 < float(post.rul[0, 0]) < float(post.rul[0, 1]) < 20000.0
    assert censor([1200.0, 20000.0, float("nan")], 20000.0) == ({"p5": 1200.0, "p50": None, "p95": None}, True)
    worn = torch.tensor([[0.2, 0.0, 0.0, 0.0, 0.0, 0.0, 0.5, 0.5]], dtype=torch.float64)
    post = tr.update(["B"], torch.tensor([0.0]), worn, scale_of(worn), torch.tensor([True]), torch.tensor([False]))
    assert float(post.rul[0, 0]) > 0
    post = tr.update(["C"], torch.tensor([0.0]), worn, scale_of(worn), torch.tensor([True]), torch.tensor([True]))
    assert float(post.rul[0, 0]) == 0.0 and float(post.rul[0, 1]) == 0.0 and float(post.rul[0, 2]) > 0


def test_an_ood_inspection_is_predicted_but_not_fused(pipeline, law):
    tr = tracker(pipeline, law)
    k = torch.tensor([[0.05, 0.0, 0.0, 0.0, 0.0, 0.0, 0.5, 0.5]], dtype=torch.float64)
    tr.update(["A"], torch.tensor([0.0]), k, scale_of(k), torch.tensor([True]))
    log_s = tr.log_s[0].clone()
    wild = torch.tensor([[0.9] * 6 + [0.5, 0.5]], dtype=torch.float64)
    post = tr.update(["A"], torch.tensor([200.0]), wild, scale_of(wild), torch.tensor([False]))
    assert torch.equal(tr.log_s[0], log_s)  # no reweighting: s untouched
    assert float(post.k_mean[0, 0]) < 0.07  # moved by the law only (~5 % in 200 h)
    first = tr.update(["B"], torch.tensor([0.0]), wild, scale_of(wild), torch.tensor([False]))
    assert not first.tracked[0] and torch.isnan(first.rul).all()  # an OOD first inspection starts nothing


def test_maintenance_restarts_the_track(pipeline, law):
    posts = run_noisy(pipeline, law, 2.0, 10)
    tr = tracker(pipeline, law)
    for i, p in enumerate(posts):  # rebuild the worn track, then restart it at a repaired state
        k = p.k_mean
        tr.update(["A"], torch.tensor([200.0 * i]), k, scale_of(k, 0.002), torch.tensor([True]))
    fresh = torch.tensor([[0.01, 0.0, 0.0, 0.0, 0.0, 0.0, 0.5, 0.5]], dtype=torch.float64)
    post = tr.update(
        ["A"], torch.tensor([2200.0]), fresh, scale_of(fresh), torch.tensor([True]), restart=torch.tensor([True])
    )
    assert abs(float(post.k_mean[0, 0]) - 0.01) < 0.01
    band = post.rate_scale[0]
    assert float(band[2] / band[0]) > math.exp(2 * 1.645 * 0.35) * 0.8  # back to the fleet prior


def test_an_actuators_track_does_not_depend_on_its_batch(pipeline, law):
    k = torch.tensor(
        [[0.05, 0.0, 0.0, 0.0, 0.0, 0.0, 0.5, 0.5], [0.02, 0.01, 0.0, 0.0, 0.0, 0.0, 0.5, 0.5]], dtype=torch.float64
    )
    together, alone = tracker(pipeline, law), tracker(pipeline, law)
    for i in range(3):
        a = together.update(["A", "B"], torch.tensor([200.0 * i] * 2), k, scale_of(k), torch.tensor([True, True]))
        b = alone.update(["B"], torch.tensor([200.0 * i]), k[1:], scale_of(k[1:]), torch.tensor([True]))
    torch.testing.assert_close(a.k_mean[1], b.k_mean[0], rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(a.rate_scale[1], b.rate_scale[0], rtol=1e-12, atol=1e-12)


def exact_rate_scale_band(law: DamageLaw, k_hat: torch.Tensor, sd: torch.Tensor, hours: list[float]) -> list[float]:
    """5/50/95 % of s of the exact posterior for noise-free paths, Gaussian errors of std ``sd`` (8,), a flat
    prior on the initial k and the lognormal prior on s: per s the measurements are a linear regression on the
    initial k, whose marginal likelihood is closed form (no clamped estimate: the damage stays above 0)."""
    comps = [0, 1, 2, 3, 4, 5, 7]
    grid = torch.exp(torch.linspace(-1.5, 1.5, 241, dtype=torch.float64))
    w = 1.0 / sd[comps] ** 2
    y = (k_hat - law.nominal)[:, comps]
    t = torch.tensor(hours, dtype=torch.float64)
    a = torch.linalg.matrix_exp(law.rate * (grid.view(-1, 1) * t).reshape(-1, 1, 1))  # (G T, 8, 8)
    a = a.reshape(len(grid), len(hours), 8, 8)[:, :, comps][:, :, :, comps]
    h = torch.einsum("gtji,j,gtjk->gik", a, w, a)
    x = torch.linalg.solve(h, torch.einsum("gtji,j,tj->gi", a, w, y))
    resid = ((y - torch.einsum("gtij,gj->gti", a, x)) ** 2 * w).sum((1, 2))
    log_s = grid.log()
    log_p = -0.5 * resid - 0.5 * torch.logdet(h) - 0.5 * (log_s / law.rate_scale_sigma) ** 2 - log_s
    cdf = torch.softmax(log_p, 0).cumsum(0)
    return [float(grid[int(torch.searchsorted(cdf, torch.tensor(q, dtype=cdf.dtype)))]) for q in (0.05, 0.5, 0.95)]


def test_the_rate_scale_band_is_the_exact_posteriors_and_covers_the_true_s(law):
    """20 actuators with s from the fleet prior, 8 inspections: the filter's 5/50/95 % of s agree with the exact
    posterior's, and its 5-95 % band covers the true s of at least 16 (resampling every inspection, the first
    version covered ~40 %)."""
    g = torch.Generator().manual_seed(1)
    n_act, n = 20, 8
    s_true = torch.exp(law.rate_scale_sigma * torch.randn(n_act, generator=g, dtype=torch.float64))
    k0 = law.nominal.repeat(n_act, 1)
    k0[:, :6] = 0.05 + 0.05 * torch.rand(n_act, 6, generator=g, dtype=torch.float64)
    tr = Tracker(law, None, TrackerSettings(n_particles=256, rul_particles=16))
    ids, k_hats = [f"S{i}" for i in range(n_act)], []
    for i in range(n):
        k = law.nominal + law.propagate(k0 - law.nominal, s_true * 200.0 * i)
        k_hat = (k + HALF_WIDTH / 1.645 * torch.randn(n_act, 8, generator=g, dtype=torch.float64)).clamp(0, 1)
        k_hat[:, 6] = k[:, 6]
        k_hats.append(k_hat)
        post = tr.update(
            ids,
            torch.full((n_act,), 200.0 * i),
            k_hat,
            scale_of(k_hat, HALF_WIDTH * 2.132 / 1.645),
            torch.ones(n_act, dtype=torch.bool),
        )
    band = post.rate_scale
    assert int(((band[:, 0] <= s_true) & (s_true <= band[:, 2])).sum()) >= 16
    sd = scale_of(k_hats[0][:1], HALF_WIDTH * 2.132 / 1.645)[0]
    for a in range(0, n_act, 4):  # five of them against the exact posterior
        exact = exact_rate_scale_band(law, torch.stack([k[a] for k in k_hats]), sd, [200.0 * i for i in range(n)])
        assert max(abs(math.log(f / e)) for f, e in zip(band[a].tolist(), exact)) < 0.05, (band[a], exact)


def test_the_warm_started_crossing_is_the_cold_one(pipeline, law):
    rul = ParticleRUL(pipeline, law, bisections=10)
    g = torch.Generator().manual_seed(3)
    k = torch.tensor(NOMINAL, dtype=torch.float64).repeat(16, 1)
    k[:, :6] = 0.02 + 0.1 * torch.rand(16, 6, generator=g, dtype=torch.float64)
    tau_max = torch.full((16,), 8 * law.horizon_hours, dtype=torch.float64)
    cold = rul.wear_clock_crossing(k, float(tau_max[0]))
    guess = cold * (1.0 + 0.05 * torch.randn(16, generator=g, dtype=torch.float64))  # a noisy previous one
    guess[:3] = float("nan")  # unknown: cold search
    torch.testing.assert_close(rul.warm_crossing(k, guess, tau_max), cold, rtol=2e-3, atol=1.0)


def test_a_particle_faulty_now_has_no_life_left_whatever_its_previous_crossing(pipeline, law):
    """The score need not stay faulty along a path (phi_a's bandwidth can come back above its limit): a particle
    faulty now has RUL 0 even when its warm start points at a later healthy -> faulty crossing."""

    class Beyond(ParticleRUL):  # faulty from k1 = 0.5 on
        def score(self, k):
            return torch.where(k.clamp(0.0, 1.0)[:, 0] >= 0.5, -1.0, 1.0).to(torch.float64)

    class TwoBands(Beyond):  # and for k1 in [0.2, 0.3]
        def score(self, k):
            x = k.clamp(0.0, 1.0)[:, 0]
            return torch.where((x >= 0.2) & (x <= 0.3), -1.0, super().score(k))

    rul = TwoBands(pipeline, law, bisections=10)
    k = torch.tensor(NOMINAL, dtype=torch.float64).repeat(3, 1)
    k[:, 0] = torch.tensor([0.25, 0.25, 0.35])  # faulty now, faulty now, healthy now
    tau_max = torch.full((3,), law.horizon_hours, dtype=torch.float64)
    later = Beyond(pipeline, law, bisections=10).wear_clock_crossing(k, law.horizon_hours)  # crossings of 0.5
    assert (later > 0).all() and (later < law.horizon_hours).all()
    out = rul.warm_crossing(k, torch.stack([later[0], torch.tensor(HUGE, dtype=torch.float64), later[2]]), tau_max)
    assert out[:2].tolist() == [0.0, 0.0]
    torch.testing.assert_close(out[2:], later[2:], rtol=0.0, atol=rul.step)  # a step score: within a grid step


def test_the_records_verdict_is_a_likelihood_ratio_on_the_particles_already_faulty(pipeline, law):
    """P(faulty) p Platt-scaled at fault rate pi is the posterior odds of the record alone: its likelihood ratio is
    (p / (1 - p)) / (pi / (1 - pi)), 1 for a record that says no more than the prior. Half the particles past the
    boundary: the median RUL is 0 unless the record says healthy, and a record at the prior changes nothing."""
    from phm_torch.tracking.measurement import verdict_odds

    odds = verdict_odds([0.9, 0.5, 0.2, None], 0.5)
    torch.testing.assert_close(odds, torch.tensor([9.0, 1.0, 0.25, 1.0], dtype=torch.float64))
    assert float(verdict_odds([0.714], 0.714)[0]) == pytest.approx(1.0)
    assert verdict_odds([0.3], None) is None
    with pytest.raises(ValueError, match="verdict_prior_faulty"):
        verdict_odds([0.3], 1.0)

    class Beyond(ParticleRUL):  # faulty from k1 = 0.5 on
        def score(self, k):
            return torch.where(k.clamp(0.0, 1.0)[:, 0] >= 0.5, -1.0, 1.0).to(torch.float64)

    rul = Beyond(pipeline, law, bisections=10)
    k = torch.tensor(NOMINAL, dtype=torch.float64).repeat(1, 16, 1)
    k[0, :8, 0], k[0, 8:, 0] = 0.6, 0.3  # half of the cloud already faulty
    s = torch.ones(1, 16, dtype=torch.float64)
    q = {r: rul(k, s, faulty_odds=torch.tensor([r], dtype=torch.float64))[0][0, 1] for r in (1.0, 0.25, 4.0)}
    assert float(q[1.0]) == 0.0 and float(q[4.0]) == 0.0  # as likely faulty as not, or more: no life left
    assert float(q[0.25]) > 0.0  # the record says healthy: the healthy particles' life
    plain = rul(k, s)[0][0, 1]
    assert float(plain) == float(q[1.0])


def test_a_band_calibrated_with_the_rate_scale_has_that_share_removed_once(pipeline, law):
    from phm_torch.tracking.particle_rul import eps_log_sigmas

    lo, hi = eps_log_sigmas(pipeline, law, False)
    assert lo == hi == 0.0  # the synthetic pipeline: no band
    wide = make_pipeline()
    wide.rate_scales.copy_(torch.tensor([math.exp(1.645 * 0.5), 1.0, math.exp(-1.645 * 0.4)]))
    lo, hi = eps_log_sigmas(wide, law, True)
    assert abs(hi - math.sqrt(0.5**2 - 0.35**2)) < 1e-4 and abs(lo - math.sqrt(0.4**2 - 0.35**2)) < 1e-4
    narrow = make_pipeline()
    narrow.rate_scales.copy_(torch.tensor([math.exp(1.645 * 0.16), 1.0, math.exp(-1.645 * 0.1)]))
    assert eps_log_sigmas(narrow, law, True) == pytest.approx((0.1, 0.16), rel=1e-4)  # cannot hold s: eps alone


def test_a_pipeline_calibrated_before_the_rate_scale_tracks_s_with_the_composed_prior(pipeline):
    from phm_torch.tracking import build_tracker

    old = {k: v for k, v in damage_config().items() if k != "rate_scale_sigma"}
    tr, described = build_tracker(pipeline, {"damage": old}, damage_config(), TrackerSettings(), "test")
    assert tr.law.rate_scale_sigma == 0.35 and not described["band_included_rate_scale"]
    tr, described = build_tracker(pipeline, {"damage": damage_config()}, None, TrackerSettings(), "test")
    assert described["band_included_rate_scale"]


def test_whether_a_band_holds_the_rate_scale_is_read_from_the_damage_config_it_was_calibrated_with():
    """phm-track removes the wear-rate scale's share from a band only where its calibration held it."""
    from phm_torch.tracking.damage_law import band_includes_rate_scale

    assert band_includes_rate_scale({"damage": damage_config()})  # rate_scale_sigma 0.35
    assert not band_includes_rate_scale({"damage": {**damage_config(), "rate_scale_sigma": 0.0}})
    assert not band_includes_rate_scale(
        {"damage": {k: v for k, v in damage_config().items() if k != "rate_scale_sigma"}}
    )
    assert not band_includes_rate_scale({})  # the shipped pipeline: no damage config at all


def test_the_kalman_update_is_the_joint_one_and_a_clamped_reading_is_a_bound():
    from phm_torch.tracking import kalman

    m, c, k_hat, scale = filter_state(4, 0.3, 1e-6)
    m1, c1, ll = kalman.update(m, c, k_hat, scale)
    s_mat = c + torch.diag_embed(scale**2).unsqueeze(1)
    gain = c @ torch.linalg.inv(s_mat)
    innov = (k_hat.unsqueeze(1) - m).unsqueeze(-1)
    torch.testing.assert_close(m1, m + (gain @ innov).squeeze(-1))
    torch.testing.assert_close(c1, c - gain @ c)
    exact = -0.5 * (innov.transpose(-1, -2) @ torch.linalg.solve(s_mat, innov)).reshape(2, 3) - 0.5 * torch.logdet(
        s_mat
    )
    torch.testing.assert_close(ll - ll[:, :1], exact - exact[:, :1])  # up to a constant per row
    # k_hat clamped at 0 on a component whose prior sits at 0.02 +/- 0.01: it says k + e <= 0, so k moves down
    # and its variance shrinks, by the moments of the truncated normal; a prior far above 0 is improbable
    m0 = torch.full((1, 2, 8), 0.3, dtype=torch.float64)
    m0[0, :, 0] = torch.tensor([0.02, 0.1], dtype=torch.float64)
    c0 = torch.diag_embed(torch.full((1, 2, 8), 1e-4, dtype=torch.float64))
    k_hat0 = m0[0, 0].unsqueeze(0).clone()
    k_hat0[0, 0] = 0.0
    m2, c2, ll2 = kalman.update(m0, c0, k_hat0, torch.full((1, 8), 0.01, dtype=torch.float64))
    assert float(m2[0, 0, 0]) < 0.02 and float(c2[0, 0, 0, 0]) < 1e-4
    v = 2e-4  # var of k + e
    assert float(ll2[0, 0] - ll2[0, 1]) == pytest.approx(
        float(
            torch.special.log_ndtr(torch.tensor(-0.02 / v**0.5)) - torch.special.log_ndtr(torch.tensor(-0.1 / v**0.5))
        ),
        rel=1e-6,
    )


def test_the_boundary_timing_error_widens_the_band_of_healthy_particles_only(pipeline, law):
    """Each healthy, uncensored particle's RUL gets std x its normal added (kept above 0); a particle already past
    the boundary (RUL 0) and a censored one are untouched, so the end-of-life flag (p50 = 0) cannot move. Without
    normals, or at std 0, the RUL is the plain one."""
    k = torch.tensor(NOMINAL, dtype=torch.float64).repeat(1, 64, 1)
    k[0, :48, 0] = torch.linspace(0.1, 0.3, 48, dtype=torch.float64)  # healthy with some life left
    k[0, 48:, 0] = 0.95  # past the classifier's boundary (< 0.3 healthy): no life left
    s = torch.ones(1, 64, dtype=torch.float64)
    z = torch.randn(1, 64, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    plain = ParticleRUL(pipeline, law, bisections=8)
    jitter = ParticleRUL(pipeline, law, bisections=8, boundary_std_hours=300.0)
    q0, _, tau0 = plain(k, s)
    q1, _, tau1 = jitter(k, s, z_boundary=z)
    torch.testing.assert_close(tau1, tau0)  # the crossings (the warm starts) are the classifier's own
    assert torch.equal(jitter(k, s)[0], q0)  # no normals: no timing error
    assert torch.equal(ParticleRUL(pipeline, law, 8, 8)(k, s, z_boundary=z)[0], q0)  # std 0: none
    assert float(q0[0, 0]) == 0.0 and float(q1[0, 0]) == 0.0  # a quarter of the particles have no life left
    assert float(q1[0, 1]) > 0.0  # the healthy ones still have some, whatever their timing error
    assert float(q1[0, 2]) > float(q0[0, 2])  # the upper bound moves out by the timing error
    with pytest.raises(ValueError, match="boundary_std_hours must be finite and >= 0, got -1.0"):
        ParticleRUL(pipeline, law, boundary_std_hours=-1.0)
    with pytest.raises(ValueError, match="tracker.boundary_std_hours must be finite and >= 0"):
        TrackerSettings(boundary_std_hours=float("nan"))


def test_faulty_at_p5_flags_where_a_twentieth_of_the_posterior_is_past_the_boundary(pipeline, law):
    """An actuator near the classifier's boundary (its 400-point fit of "every damage below 0.3") read with spread:
    part of its particles are past it, so the RUL's 5 % quantile is 0 while its median is not. ``faulty_at=p5`` makes that
    inspection faulty: RUL 5 % and 50 % reported 0, the 95 % and every draw unchanged."""
    edge = torch.tensor([[0.35, 0.0, 0.0, 0.0, 0.0, 0.0, 0.5, 0.5]], dtype=torch.float64)
    args = (["A"], torch.tensor([0.0]), edge, scale_of(edge, 0.1), torch.tensor([True]), torch.tensor([False]))
    median = tracker(pipeline, law).update(*args)
    early = tracker(pipeline, law, faulty_at="p5").update(*args)
    assert float(median.rul[0, 0]) == 0.0 and float(median.rul[0, 1]) > 0.0  # p50: still healthy
    assert float(early.rul[0, 0]) == 0.0 and float(early.rul[0, 1]) == 0.0  # p5: faulty, no life left at 50 %
    torch.testing.assert_close(early.rul[0, 2], median.rul[0, 2])
    torch.testing.assert_close(early.rate_scale, median.rate_scale)
    with pytest.raises(ValueError, match="tracker.faulty_at must be one of \\['p5', 'p50'\\], got 'p25'"):
        TrackerSettings(faulty_at="p25")
