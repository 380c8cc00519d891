"""Assessment function: linearised reference loop, frequency-response measurement, margins, labels."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
import torch
from hydra.utils import instantiate

from phm_torch.assessment import (
    AssessmentFunction,
    FrequencyResponse,
    HealthRequirements,
    SineSweep,
    SweepDesign,
    linear_loop,
    margins,
    unmeasurable_counts,
)
from phm_torch.assessment.frequency_response import padded_size
from phm_torch.assessment.health import worst_margins
from phm_torch.physics import mechanics

FINE = np.geomspace(5.0, 300.0, 3000)


def _margins(freqs, l_resp, t_resp):
    m = margins(torch.as_tensor(freqs), torch.as_tensor(l_resp)[None], torch.as_tensor(t_resp)[None])
    return {k: float(v[0]) for k, v in m.as_dict().items()}


@pytest.fixture(scope="module")
def shipped(compose):
    """The shipped assessment config (conf/assessment/frequency_response.yaml), uncompiled."""
    cfg = compose("generate")
    return cfg.assessment


def _assessment(params, node, **sweep_changes) -> AssessmentFunction:
    sweep = instantiate(node.sweep)
    sweep = SineSweep(**{**vars(sweep), **sweep_changes})
    return AssessmentFunction(params, sweep, instantiate(node.requirements))


def test_linear_loop_matches_datasheet(params):
    # ema_reference.md §1: crossover ~28 Hz, PM ~74 deg, GM ~10 dB (linear sampled-data analysis).
    lp = linear_loop(params)
    assert np.abs(np.linalg.eigvals(lp.closed.A)).max() < 1.0  # stable closed loop
    m = _margins(FINE, *lp.response(FINE))
    assert m["crossover_hz"] == pytest.approx(28.0, abs=1.0)
    assert m["phase_margin_deg"] == pytest.approx(74.0, abs=2.0)
    assert m["gain_margin_db"] == pytest.approx(10.0, abs=0.7)
    # K_pos x 1.5 (k8 = 1) costs 20 log10(1.5) = 3.5 dB of gain margin, the phase crossover unchanged
    m15 = _margins(FINE, *linear_loop(params, 1.5).response(FINE))
    assert m["gain_margin_db"] - m15["gain_margin_db"] == pytest.approx(20 * math.log10(1.5), abs=0.05)


def test_margin_interpolation_on_the_shipped_grid(params, shipped):
    # The coarse shipped grid (derived for this actuator) recovers the fine-grid margins of the linear loop.
    lp = linear_loop(params)
    coarse = np.asarray(instantiate(shipped.sweep).resolve(params).frequencies, dtype=float)
    fine, got = _margins(FINE, *lp.response(FINE)), _margins(coarse, *lp.response(coarse))
    assert got["crossover_hz"] == pytest.approx(fine["crossover_hz"], rel=0.01)
    assert got["phase_margin_deg"] == pytest.approx(fine["phase_margin_deg"], abs=0.5)
    assert got["gain_margin_db"] == pytest.approx(fine["gain_margin_db"], abs=0.2)
    assert got["bandwidth_hz"] == pytest.approx(fine["bandwidth_hz"], rel=0.03)


def test_margin_conventions():
    f = torch.tensor([1.0, 10.0, 100.0])
    never = torch.tensor([[0.5 + 0j, 0.4 + 0j, 0.3 + 0j]])  # |L| < 1 everywhere, phase 0
    t_high = torch.tensor([[1.0 + 0j, 0.9 + 0j, 0.8 + 0j]])  # |T| never below -3 dB
    m = margins(f, never, t_high)
    assert math.isnan(float(m.crossover_hz[0])) and math.isnan(float(m.gain_margin_db[0]))
    assert math.isinf(float(m.bandwidth_hz[0]))
    t_low = torch.tensor([[0.5 + 0j, 0.4 + 0j, 0.3 + 0j]])  # already below at the first point
    assert math.isnan(float(margins(f, never, t_low).bandwidth_hz[0]))
    ph = torch.tensor([-90.0, -170.0, -190.0]) * math.pi / 180
    loop = torch.polar(torch.tensor([2.0, 0.5, 0.25]), ph)[None]
    m = margins(f, loop, t_high)
    assert float(m.crossover_hz[0]) == pytest.approx(10 ** (1 / 2), rel=1e-6)  # |L| dB falls 6 -> -6 over a decade
    assert float(m.phase_crossover_hz[0]) == pytest.approx(10**1.5, rel=1e-6)
    assert float(m.gain_margin_db[0]) == pytest.approx(-20 * math.log10(math.sqrt(0.5 * 0.25)), abs=1e-5)


def test_a_reading_stuck_in_dry_friction_bounds_the_gain_margin_instead_of_voiding_it():
    """A ball screw's damaged loop, read at three rotor positions (measured, rounded): past its crossover the phase
    nears -180 deg at -18 dB, then the output sticks (-47 dB and below, phase noise). With every reading, the phase
    never falls through -180 deg on the grid at one position: gain margin nan, the vector faulty, healthy again at
    the next inspection. Below the floor a reading is no response: the margin is the -|L| of the last responding
    one, a lower bound; a loop crossing -180 deg while it responds keeps its margin, a wholly responding grid its nan."""
    f = torch.tensor([20.0, 28.0, 36.0, 46.0, 60.0, 80.0])
    mag_db = torch.tensor([-6.1, -9.1, -17.6, -47.4, -319.7, -313.4])
    phase = torch.tensor([-142.5, -165.7, -176.6, -111.7, -88.9, -124.1])
    stuck = torch.polar(10 ** (mag_db / 20), torch.deg2rad(phase))[None].to(torch.complex128)
    t = torch.ones_like(stuck)
    assert math.isnan(float(margins(f, stuck, t).gain_margin_db[0]))  # every reading counts: "unmeasurable"
    bounded = margins(f, stuck, t, no_response_db=-40.0)
    assert float(bounded.gain_margin_db[0]) == pytest.approx(17.6, abs=1e-6) and math.isnan(
        float(bounded.phase_crossover_hz[0])
    )
    crossing = torch.tensor([-142.5, -165.7, -185.0, -111.7, -88.9, -124.1])  # falls through -180 while responding
    loop = torch.polar(10 ** (mag_db / 20), torch.deg2rad(crossing))[None].to(torch.complex128)
    torch.testing.assert_close(
        margins(f, loop, t, no_response_db=-40.0).stacked(), margins(f, loop, t).stacked(), equal_nan=True
    )
    responding = torch.polar(10 ** (mag_db.clamp(min=-30.0) / 20), torch.deg2rad(phase))[None].to(torch.complex128)
    assert math.isnan(float(margins(f, responding, t, no_response_db=-40.0).gain_margin_db[0]))
    with pytest.raises(ValueError, match="no_response_db must be a negative level"):
        SineSweep((1.0, 2.0), 1e-3, 4, 2, 0.02, 1, 4, False, no_response_db=3.0)


def test_the_no_response_floor_leaves_the_reference_labels_as_they_were(params, shipped):
    """Stores labelled before the floor existed are read as labelled with it (assessment_record.SWEEP_DEFAULTS):
    on the reference actuator it must change no label (measured: 0 of 512 of the paper store's vectors, the
    unmeasurable gain margins 93 -> 15). Here on 48 importance-sampled-like vectors at every rotor position."""
    g = torch.Generator().manual_seed(3)
    k = torch.rand(48, 8, generator=g, dtype=torch.float64) ** 4  # mostly near nominal, a few heavy faults
    k[:, 6] = torch.rand(48, generator=g, dtype=torch.float64)
    k[:, 7] = 0.5 + 0.5 * (2 * torch.rand(48, generator=g, dtype=torch.float64) - 1) ** 3  # drift about nominal 0.5
    with_floor = _assessment(params, shipped, compile=False)
    without = _assessment(params, shipped, compile=False, no_response_db=None)
    assert with_floor.sweep.no_response_db == -40.0 and labelling_default() == -40.0
    a, b = with_floor(k), without(k)
    assert torch.equal(a.healthy, b.healthy)
    assert 0.1 < float(a.healthy.double().mean()) < 0.9  # both classes present: the comparison says something


def labelling_default() -> float:
    from phm_torch.assessment_record import labelling

    return labelling({"sweep": {}})["sweep"]["no_response_db"]


def _linear_transmission(state, plant):
    n = plant.gear_ratio
    return plant.output_stiffness * (state.theta_m / n - state.theta_u) + plant.output_damping * (
        state.omega_m / n - state.omega_u
    )


def test_measurement_recovers_the_linear_loop(params, monkeypatch):
    # With the nonlinearities removed (no dry friction, no backlash, a bilateral output-stage contact),
    # the sine-sweep measurement of the LF simulation equals the linear sampled-data analysis.
    monkeypatch.setattr(mechanics, "transmission_torque", _linear_transmission)
    lin_params = params.replace(coulomb_friction=0.0, static_friction=0.0, backlash=0.0)
    sweep = SineSweep((20.0, 40.0, 80.0, 110.0), 2e-4, 4, 2, 0.02, 1, 4, False)
    fr = FrequencyResponse(lin_params, sweep)
    r = fr.measure(torch.tensor([params.nominal_faults]))
    l_ref, t_ref = linear_loop(params).response(fr.frequencies.numpy())
    gain_err = 20 * np.log10(np.abs(r.open_loop[0].numpy()) / np.abs(l_ref))
    phase_err = np.degrees(np.angle(r.open_loop[0].numpy() / l_ref))
    assert np.abs(gain_err).max() < 0.3  # dB
    assert np.abs(phase_err).max() < 2.5  # deg (semi-implicit mechanics at 100 us)
    assert np.abs(r.closed_loop[0].numpy() - t_ref).max() < 0.04


def test_nominal_against_linear_analysis_and_labels(params, shipped):
    # The shipped assessment (nonlinear LF at the 8e-5 rad test amplitude) against the linear analysis,
    # with the tolerances of docs/dataset.md: dry friction lowers the low-frequency loop gain (crossover
    # -30 %, PM +5 deg), the unilateral output-stage contact lowers the gain margin (-2 dB).
    af = _assessment(params, shipped)
    lin = _margins(FINE, *linear_loop(params).response(FINE))
    nom = {k: float(v[0]) for k, v in af.nominal.as_dict().items()}
    assert nom["crossover_hz"] == pytest.approx(lin["crossover_hz"], rel=0.35)
    assert nom["phase_margin_deg"] == pytest.approx(lin["phase_margin_deg"], abs=8.0)
    assert nom["gain_margin_db"] == pytest.approx(lin["gain_margin_db"], abs=2.5)
    assert nom["phase_crossover_hz"] == pytest.approx(lin["phase_crossover_hz"], rel=0.1)
    # labels: nominal healthy with margin; too much gain (GM), too little gain (bandwidth), big backlash
    k0 = list(params.nominal_faults)
    cases = [k0, k0[:7] + [1.0], k0[:7] + [0.0], [0.0, 1.0] + k0[2:]]
    res = af(torch.tensor(cases))
    assert res.healthy.tolist() == [True, False, False, False]
    m = res.margins
    assert float(m.gain_margin_db[0]) >= 6.0 + 2.0 and float(m.phase_margin_deg[0]) >= 45.0 + 20.0
    assert float(m.gain_margin_db[1]) < 6.0
    assert not float(m.bandwidth_hz[2]) >= 0.9 * af.nominal_bandwidth_hz  # nan: below -3 dB already at 12 Hz
    assert af.vectors == 4 and af.wall_s > 0


@pytest.mark.parametrize(
    "change, field",
    [
        ({"amplitude": 0.0}, "assessment.sweep.amplitude"),
        ({"frequencies": (10.0, 5.0)}, "assessment.sweep.frequencies"),
        ({"cycles": 2, "measure_cycles": 2}, "assessment.sweep.cycles"),
        ({"group_size": 0}, "assessment.sweep.group_size"),
        ({"tolerance": 0.0}, "assessment.sweep.tolerance"),
        ({"tolerance": True}, "assessment.sweep.tolerance"),
        ({"max_extensions": -1}, "assessment.sweep.max_extensions"),
        ({"refine": 1.5}, "assessment.sweep.refine"),
    ],
)
def test_bad_sweep(change, field):
    args = {
        "frequencies": (10.0, 20.0),
        "amplitude": 1e-4,
        "cycles": 4,
        "measure_cycles": 2,
        "min_duration": 0.0,
        "substeps": 1,
        "group_size": 2,
        "compile": False,
        **change,
    }
    with pytest.raises(ValueError, match=field):
        SineSweep(**args)


@pytest.mark.parametrize(
    "change, field",
    [
        ({"bandwidth_fraction": 1.5}, "bandwidth_fraction"),
        ({"phase_margin_deg": float("nan")}, "phase_margin_deg"),
        ({"gain_margin_db": -1.0}, "gain_margin_db"),
    ],
)
def test_bad_requirements(change, field):
    with pytest.raises(ValueError, match=f"assessment.requirements.{field}"):
        HealthRequirements(**{"phase_margin_deg": 45.0, "gain_margin_db": 6.0, "bandwidth_fraction": 0.9, **change})


@pytest.mark.slow
def test_healthy_fraction_of_the_importance_sampled_set(params, shipped):
    # docs/dataset.md: 15-40 % of the importance-sampled training set is healthy (paper: 123 of 500).
    from phm_torch.data.sampling import ImportanceSampler

    af = _assessment(params, shipped, compile=True)
    k = ImportanceSampler(params.nominal_faults, (6,), 1.0).sample(1024, 11)
    frac = float(af(torch.tensor(k)).healthy.double().mean())
    assert 0.15 <= frac <= 0.40


# -- the sweep derived from the actuator (frequencies: auto, amplitude: auto) ----------------------------------


@pytest.mark.parametrize(
    "changes", [{}, {"gear_ratio": 400.0}, {"user_inertia": 0.8}, {"gear_ratio": 100.0, "supply_voltage": 56.0}]
)
def test_derived_grid_brackets_the_loop(params, changes):
    # The grid spans the linear loop's crossover, phase crossover and -3 dB bandwidth with margin on both
    # sides, for the reference and for actuators whose crossovers move by ~2x.
    p = params.replace(**changes)
    sweep = instantiate_sweep().resolve(p)
    f = np.asarray(sweep.frequencies)
    m = _margins(FINE, *linear_loop(p).response(FINE))
    lo = min(m["crossover_hz"], m["phase_crossover_hz"], m["bandwidth_hz"])
    hi = max(m["crossover_hz"], m["phase_crossover_hz"], m["bandwidth_hz"])
    assert f[0] <= lo / 2.0 and f[-1] >= hi * 1.5
    assert np.all(np.diff(np.log10(f)) <= 1 / 12 + 1e-3)  # 12 points per decade or denser
    coarse = _margins(f, *linear_loop(p).response(f))  # and the coarse grid measures the loop
    assert coarse["crossover_hz"] == pytest.approx(m["crossover_hz"], rel=0.02)
    assert coarse["phase_crossover_hz"] == pytest.approx(m["phase_crossover_hz"], rel=0.02)


def instantiate_sweep(**changes) -> SineSweep:
    return SineSweep("auto", "auto", 4, 2, 0.02, 1, 4, False, **changes)


def test_derived_grid_follows_the_crossovers(params):
    # gear ratio x2 halves the loop gain: the crossover falls 2.16x (28 -> 12.9 Hz), the phase crossover
    # stays; the grid's lower end follows the crossover, its upper end the phase crossover.
    ref = instantiate_sweep().resolve(params).frequencies
    slow = instantiate_sweep().resolve(params.replace(gear_ratio=400.0)).frequencies
    assert ref[0] / slow[0] == pytest.approx(27.88 / 12.91, rel=0.02)
    assert slow[-1] / ref[-1] == pytest.approx(90.41 / 89.11, rel=0.02)
    heavy = instantiate_sweep().resolve(params.replace(user_inertia=0.8)).frequencies  # resonance 79 -> 41 Hz
    assert heavy[-1] < 0.65 * ref[-1]


def test_derived_sweep_of_the_reference(params):
    # The reference actuator gets back the hand-tuned sweep: 12..160 Hz (14 points then, 15 now), and the
    # amplitude 4 x T_s / (2 k_e K_w K_pos) = 7.96e-5 rad (8e-5 then), friction the active bound.
    sweep = instantiate_sweep().resolve(params)
    assert sweep.frequencies[0] == pytest.approx(12.0, rel=0.02) and sweep.frequencies[-1] == pytest.approx(
        160, rel=0.02
    )
    assert len(sweep.frequencies) == 15
    expected = 4 * params.static_friction / (2 * params.back_emf_constant * params.speed_gain * params.position_gain)
    assert sweep.amplitude == pytest.approx(expected, rel=1e-3) and sweep.amplitude == pytest.approx(8e-5, rel=0.01)
    # explicit values win; doubling the friction doubles the amplitude
    fixed = SineSweep((10.0, 20.0), 1e-4, 4, 2, 0.02, 1, 4, False)
    assert fixed.resolve(params) is fixed
    part = SineSweep((10.0, 20.0), "auto", 4, 2, 0.02, 1, 4, False).resolve(params)
    assert part.frequencies == (10.0, 20.0) and part.amplitude == pytest.approx(expected, rel=1e-3)
    rough = params.replace(static_friction=2 * params.static_friction, coulomb_friction=2 * params.coulomb_friction)
    assert instantiate_sweep().resolve(rough).amplitude == pytest.approx(2 * sweep.amplitude, rel=1e-3)


def test_derived_amplitude_refused_against_the_limits(params):
    # friction so large that the break-away amplitude exceeds 1 % of the stroke: refused, naming the field
    sticky = params.replace(static_friction=3.0, coulomb_friction=3.0)
    with pytest.raises(ValueError, match="assessment.sweep.amplitude: auto"):
        instantiate_sweep().resolve(sticky)


def test_a_speed_limit_that_cannot_carry_the_amplitude_lowers_the_grids_top(params):
    """A long-stroke transmission (a ball screw, user side in metres: gear ratio 2 pi / lead ~ 1,600) or a low speed
    limit: the derived amplitude at the top of the grid would need more motor speed than half the limit. The top comes
    down to where it does not, keeping min_high_margin (1.25) above the phase crossover; below that, refused."""
    design = SweepDesign()
    fig = design.loop_figures(params)
    f_top = max(fig["phase_crossover_hz"], fig["bandwidth_hz"])
    shipped = instantiate_sweep().resolve(params)
    amp = design.lower_amplitude(params)
    assert shipped.amplitude == pytest.approx(amp, rel=1e-3)

    def speed_for(f_hz: float) -> float:  # the speed limit whose half carries amp at f_hz
        return 2.0 * math.pi * f_hz * amp * params.gear_ratio / design.limit_fraction

    slow = params.replace(speed_limit=speed_for(1.5 * f_top))
    lowered = instantiate_sweep().resolve(slow)
    assert lowered.frequencies[-1] == pytest.approx(1.5 * f_top, rel=2e-3)  # not 1.8 x
    assert lowered.frequencies[-1] < shipped.frequencies[-1]
    assert lowered.frequencies[0] == shipped.frequencies[0] and lowered.amplitude == shipped.amplitude
    # the loop figures do not depend on the (saturating) speed limit: the same linear loop, only the top moved
    assert design.loop_figures(slow) == fig
    # an explicit amplitude is what the top is checked against
    explicit = SineSweep("auto", 0.5 * amp, 4, 2, 0.02, 1, 4, False).resolve(slow)
    assert explicit.frequencies[-1] == shipped.frequencies[-1]
    # too slow even at 1.25 x the phase crossover: refused, naming the speed limit
    with pytest.raises(ValueError, match="assessment.sweep.amplitude: auto.*speed limit"):
        instantiate_sweep().resolve(params.replace(speed_limit=speed_for(1.1 * f_top)))
    with pytest.raises(ValueError, match="min_high_margin"):
        SweepDesign(min_high_margin=2.0)


def test_unmeasurable_counts():
    # nan = no crossing on the grid (counted, labelled faulty); inf bandwidth = above the grid (a bound, not counted)
    nan, inf = math.nan, math.inf
    m = np.array([[20, 70, 80, 9, 70], [nan, nan, 80, 9, 70], [20, 70, nan, nan, inf], [nan, nan, nan, nan, nan]])
    assert unmeasurable_counts(m) == {"phase_margin": 2, "gain_margin": 2, "bandwidth": 1}
    req = HealthRequirements(45.0, 6.0, 0.9)
    from phm_torch.assessment import Margins

    healthy = req.healthy(Margins(*torch.as_tensor(m).T), 70.0)
    assert healthy.tolist() == [True, False, False, False]


@pytest.mark.parametrize(
    "change, field",
    [
        ({"frequencies": "sometimes"}, "assessment.sweep.frequencies"),
        ({"amplitude": "big"}, "assessment.sweep.amplitude"),
    ],
)
def test_bad_auto_sweep(change, field):
    args = {
        "frequencies": "auto",
        "amplitude": "auto",
        "cycles": 4,
        "measure_cycles": 2,
        "min_duration": 0.0,
        "substeps": 1,
        "group_size": 2,
        "compile": False,
        **change,
    }
    with pytest.raises(ValueError, match=field):
        SineSweep(**args)


@pytest.mark.parametrize(
    "change, field",
    [
        ({"low_margin": 1.0}, "low_margin"),
        ({"high_margin": float("nan")}, "high_margin"),
        ({"points_per_decade": 1}, "points_per_decade"),
        ({"stroke_fraction": 0.0}, "stroke_fraction"),
        ({"friction_factor": -1.0}, "friction_factor"),
    ],
)
def test_bad_sweep_design(change, field):
    with pytest.raises(ValueError, match=f"assessment.sweep.design.{field}"):
        SweepDesign(**change)


# three inspections 200 h apart along one run-to-failure history (seed 33, actuator A009), every damage growing
A009_PATH = [
    [0.0656, 0.0531, 0.0861, 0.0805, 0.0656, 0.0534, 0.9053, 0.4821],
    [0.0747, 0.0617, 0.0953, 0.0901, 0.0758, 0.0584, 0.9053, 0.4809],
    [0.0853, 0.0709, 0.1058, 0.1015, 0.0874, 0.0631, 0.9053, 0.4797],
]


@pytest.mark.slow  # 40-100 s on 2 cores
def test_a_denser_grid_reads_the_margins_monotonically_along_a_damage_path(params, shipped):
    """docs/prognostics.md, 'What the histories leave to know': at 36 points per decade the bandwidth and the gain
    margin fall steadily as the damage grows (the shipped 12 per decade read them 2-4 Hz and about 1 dB off near
    the closed-loop resonance), and they agree with a grid twice as fine within 0.5 Hz and 0.3 dB."""
    design = instantiate(shipped.sweep.design)
    read = {}
    for ppd in (36.0, 72.0):
        sweep = instantiate(shipped.sweep)  # one rest angle: the grid's density is what is tested
        sweep = SineSweep(
            **{
                **vars(sweep),
                "rotor_positions": 1,
                "design": type(design)(**{**vars(design), "points_per_decade": ppd}),
            }
        )
        m = AssessmentFunction(params, sweep, instantiate(shipped.requirements))(torch.tensor(A009_PATH)).margins
        read[ppd] = (m.bandwidth_hz.numpy(), m.gain_margin_db.numpy())
    for bw, gm in read.values():
        assert np.all(np.diff(bw) < 0) and np.all(np.diff(gm) < 0)
    (bw, gm), (bw_fine, gm_fine) = read[36.0], read[72.0]
    assert np.abs(bw - bw_fine).max() < 0.5 and np.abs(gm - gm_fine).max() < 0.3


@pytest.mark.slow  # refinement is off in the shipped sweep; ~40 s
def test_refinement_reads_the_margins_of_a_fine_grid_from_a_coarse_one(params, monkeypatch):
    # The linear loop (nonlinearities removed, so every response settles) measured on 4 points per decade: a
    # round of refinement puts a measured point at each crossing. One round reads the gain and phase crossovers
    # and margins of a 40-per-decade grid measured the same way; the bandwidth, at the knee where the flat |T|
    # turns steep, gains about 3x per round (grid 2.4 %, one round 0.8 %, two rounds 0.2 % off).
    monkeypatch.setattr(mechanics, "transmission_torque", _linear_transmission)
    lin_params = params.replace(coulomb_friction=0.0, static_friction=0.0, backlash=0.0)
    k = torch.tensor([params.nominal_faults])
    coarse = (12.0, 21.5, 38.5, 69.0, 124.0, 222.0)
    got = {}
    for refine, freqs in ((0, coarse), (1, coarse), (2, coarse), ("fine", tuple(np.geomspace(12, 222, 52)))):
        rounds = 0 if refine == "fine" else refine
        fr = FrequencyResponse(lin_params, SineSweep(freqs, 2e-4, 4, 2, 0.02, 1, 6, False, refine=rounds))
        r = fr.read(k)
        assert r.frequencies.shape == ((len(freqs),) if rounds == 0 else (1, len(freqs) + 3 * rounds))
        got[refine] = {n: float(v[0]) for n, v in margins(r.frequencies, r.open_loop, r.closed_loop).as_dict().items()}
    fine = got["fine"]
    for name in ("crossover_hz", "phase_crossover_hz"):
        assert got[1][name] == pytest.approx(fine[name], rel=0.003), name
    assert got[1]["phase_margin_deg"] == pytest.approx(fine["phase_margin_deg"], abs=0.2)
    assert got[1]["gain_margin_db"] == pytest.approx(fine["gain_margin_db"], abs=0.1)
    bw_error = [abs(got[r]["bandwidth_hz"] / fine["bandwidth_hz"] - 1) for r in (0, 1, 2)]
    assert bw_error[0] > 0.015 and bw_error[1] < bw_error[0] / 2 and bw_error[2] < 0.004
    assert abs(got[0]["gain_margin_db"] - fine["gain_margin_db"]) > 0.5  # the grid alone is off


@pytest.mark.slow  # settling is off in the shipped sweep; ~20 s
def test_settling_makes_the_response_independent_of_the_batching(params, shipped):
    """A degraded actuator (A009's second inspection) near its -3 dB bandwidth: read after a fixed 4 cycles, |T|
    depends on whether a frequency is simulated for its own 4 cycles or for the longest test of its group (the
    transient is still there); with extensions until L and T settle, both batchings agree to 0.05 dB and are
    marked settled. At 77 Hz, past the degraded loop's resonance, the response never becomes periodic: it is
    marked unsettled and counted, not passed off as a measurement."""
    k = torch.tensor(A009_PATH[1:2])
    base = {**vars(instantiate(shipped.sweep)), "frequencies": (60.0, 65.0, 70.0), "amplitude": 7.96e-5}
    gain = {}
    for extensions in (0, 3):
        for group in (1, 3):
            fr = FrequencyResponse(params, SineSweep(**{**base, "group_size": group, "max_extensions": extensions}))
            r = fr.measure(k)
            gain[extensions, group] = 20 * np.log10(np.abs(r.closed_loop[0].numpy()))
            assert bool(r.settled.all()) == (extensions > 0)
    assert np.abs(gain[3, 1] - gain[3, 3]).max() < 0.05
    assert np.abs(gain[0, 1] - gain[0, 3]).max() > 0.3  # the test can fail: unsettled readings show the batching
    assert gain[3, 1][2] - gain[0, 1][2] > 0.6  # 70 Hz: settled ~-1.5 dB, 4 cycles alone read -2.41 dB
    fr = FrequencyResponse(params, SineSweep(**{**base, "frequencies": (76.6, 80.0), "max_extensions": 2}))
    assert not bool(fr.measure(k).settled[0, 0]) and fr.unsettled >= 1


@pytest.mark.slow  # 40-100 s on 2 cores
def test_labels_read_from_the_transient_are_uncertain(params, shipped):
    """A009's three inspections along its damage path (the shipped sweep, uncompiled). Read after a fixed 4 cycles
    (``max_extensions`` 0, ``refine`` 0, the shipped reading),
    the labels are not monotone along the path (healthy, faulty, healthy again) and two of the three differ from
    what the window before reads: the transient decides them, and ``uncertain`` says so. Settled and refined,
    the labels follow the damage (healthy, healthy, faulty) and at most the one nearest the bandwidth
    requirement, read from a response that is not periodic, stays uncertain."""
    k = torch.tensor(A009_PATH)
    # one rest angle: the transient is what is tested (at three, the third inspection fails at another angle)
    sweep = dataclasses.replace(instantiate(shipped.sweep), compile=False, rotor_positions=1)
    requirements = instantiate(shipped.requirements)
    assert (sweep.max_extensions, sweep.refine) == (0, 0)  # the shipped sweep reads 4 cycles (docs/dataset.md)
    fixed = AssessmentFunction(params, sweep, requirements)(k)
    settled_fn = AssessmentFunction(params, dataclasses.replace(sweep, max_extensions=2, refine=1), requirements)
    settled = settled_fn(k)
    assert fixed.healthy.tolist() == [True, False, True]
    assert int(fixed.uncertain.sum()) >= 2
    assert settled.healthy.tolist() == [True, True, False]
    assert int(settled.uncertain.sum()) <= 1 and not bool(settled.uncertain[:2].any())
    assert settled_fn.settling()["uncertain_labels"] == int(settled.uncertain.sum())
    assert settled_fn.settling()["vectors"] == 3


@pytest.mark.slow  # extensions and refinement, compiled; ~20 s
def test_compiled_extensions_and_refinement_run_in_a_few_padded_batch_sizes(params, shipped):
    """With a compiled simulator the extensions' and refinement's varying batches are padded to a few sizes (one
    compilation per size, not per call); the padding repeats rows, so the readings equal the unpadded ones exactly.
    (Run eager here: the padding is what is tested, ``compile`` only switches it on.)"""
    k = torch.tensor(A009_PATH[1:])
    base = {**vars(instantiate(shipped.sweep)), "frequencies": (60.0, 65.0, 70.0, 77.0), "amplitude": 7.96e-5}
    sweep = SineSweep(**{**base, "compile": False, "max_extensions": 2, "refine": 1})
    plain = FrequencyResponse(params, sweep)
    padded = FrequencyResponse(params, sweep)
    padded.sweep = dataclasses.replace(sweep, compile=True)  # the padding without the compilation
    sizes = []
    run = padded.sim.run

    def recording(faults, *args, **kwargs):
        sizes.append(faults.shape[0])
        return run(faults, *args, **kwargs)

    padded.sim.run = recording
    a, b = (fr.read(k) for fr in (plain, padded))
    for name in ("frequencies", "open_loop", "closed_loop", "settled", "open_loop_before", "closed_loop_before"):
        assert torch.equal(getattr(a, name), getattr(b, name)), name
    assert padded.extensions == plain.extensions > 0
    grid = 2 * len(padded.groups[0])  # the grid's batches: every vector at every frequency of a group
    assert all(n == grid or n == padded_size(n) for n in sizes), sizes
    assert any(n != grid for n in sizes)


@pytest.mark.slow  # ~60 s on 2 cores
def test_a_vectors_settled_refined_reading_does_not_depend_on_its_batch(params, shipped):
    """Each vector's reading, settled and refined, is the same assessed alone or beside others (eager: the simulator
    is batch invariant): every simulation of a row lasts as long as its own test says, never the batch's longest.
    (The refinement once simulated a batch for its longest test, so a label depended on the other rows.)"""
    near = torch.tensor([0.05, 0.05, 0.1, 0.0, 0.0, 0.05, 0.3, 0.02], dtype=torch.float64)
    k = torch.stack([torch.tensor(A009_PATH[1]), near, torch.tensor(A009_PATH[2])]).double()
    base = {**vars(instantiate(shipped.sweep)), "frequencies": (20.0, 40.0, 70.0, 90.0), "amplitude": 7.96e-5}
    fr = FrequencyResponse(params, SineSweep(**{**base, "compile": False, "max_extensions": 1, "refine": 1}))
    together = fr.read(k)
    for i in range(len(k)):
        alone = fr.read(k[i : i + 1])
        for name in ("frequencies", "open_loop", "closed_loop", "settled"):
            a, b = getattr(together, name)[i], getattr(alone, name)[0]
            assert (
                torch.allclose(a, b, rtol=0, atol=1e-10)
                if a.is_floating_point() or a.is_complex()
                else bool(torch.equal(a, b))
            ), (i, name)


def test_a_short_in_the_phase_off_at_rest_is_invisible_and_three_rotor_positions_see_every_phase(params, shipped):
    """The sweep's few electrical degrees keep the rotor in one commutation sector: at rest at 0 phase A does not
    conduct, so a short there reads exactly the nominal margins (labelled healthy) while one in B or C fails.
    Resting the rotor at 0, 60 and 120 electrical degrees and taking the worst, each phase conducts once: nothing
    is invisible (the shorts' readings are in the next test)."""
    one = _assessment(params, shipped, rotor_positions=1)
    three = _assessment(params, shipped)  # the shipped sweep reads three positions
    assert three.sweep.rotor_positions == 3
    assert one.invisible_faults() == ["short_a"] and one.record()["invisible_faults"] == ["short_a"]
    assert three.invisible_faults() == []
    with pytest.raises(ValueError, match="rotor_positions must be an integer in \\[1, 6\\], got 0"):
        _assessment(params, shipped, rotor_positions=0)


def test_reading_stops_at_the_first_failing_rotor_position_and_labels_as_reading_every_one(params, shipped):
    """phi_a reads a vector at the next rotor position only while it passes in either window: the labels and the
    uncertain flags are those of reading every position, the margins those of the positions read (all of them for
    a healthy vector), and a batch that fails everywhere at the first position is read once. The first four rows
    are the nominal actuator and a 0.98 short in phase A, B, C: at 0 degrees alone the phase-A short reads the
    nominal margins; over the three positions the shorts read alike and fail."""
    g = torch.Generator().manual_seed(3)
    u = torch.rand(20, 8, generator=g, dtype=torch.float64)
    k = u**4 * 0.3  # near nominal: both classes
    k[:, 6] = u[:, 6]
    k[:, 7] = 0.5 + 0.1 * (u[:, 7] - 0.5)
    k[:4] = torch.tensor([params.nominal_faults] * 4, dtype=torch.float64)
    for i in range(3):
        k[1 + i, 2 + i] = 0.98
    phi = _assessment(params, shipped)
    calls = []  # the rows the second position is asked to read
    second = phi.responses[1]
    second.read = lambda kk, _read=second.read: calls.append(kk.shape[0]) or _read(kk)
    a = phi(k)
    asked = list(calls)  # the batch's own calls (the reads below ask again for every row)
    reads = [x.read(k) for x in phi.responses]
    last = worst_margins([x.margins_of(r) for x, r in zip(phi.responses, reads, strict=True)])
    before = worst_margins([x.margins_of(r.before) for x, r in zip(phi.responses, reads, strict=True)])
    bw0 = phi.nominal_bandwidth_hz
    healthy = phi.requirements.healthy(last, bw0)
    assert 4 <= int(healthy.sum()) <= 16  # both classes, so both paths are exercised
    assert torch.equal(a.healthy, healthy)
    assert torch.equal(a.uncertain, healthy != phi.requirements.healthy(before, bw0))
    assert torch.equal(a.margins.stacked()[healthy], last.stacked()[healthy])
    first = phi.responses[0].margins_of(reads[0])
    first_before = phi.responses[0].margins_of(reads[0].before)
    # the shorts: invisible in phase A at one position, alike and failing over three
    m1, m3 = first.stacked(), last.stacked()
    assert torch.equal(m1[1], m1[0]) and phi.requirements.healthy(first, bw0)[:4].tolist() == [True, True, False, False]
    assert a.healthy[:4].tolist() == [True, False, False, False]
    assert torch.allclose(m3[1], m3[2], rtol=1e-6) and torch.allclose(m3[2], m3[3], rtol=1e-6)
    assert torch.allclose(m3[0], m1[0], rtol=1e-9)  # no fault, no position dependence
    assert float(m3[1, 4]) < 0.5 * float(m3[0, 4])  # the short's bandwidth loss, now seen
    passing = phi.requirements.healthy(first, bw0) | phi.requirements.healthy(first_before, bw0)
    assert asked == [int(passing.sum())] and int(passing.sum()) < k.shape[0]


def test_label_check_names_the_invisible_fault_and_the_play_the_sweep_measures(params, shipped):
    """scripts/check_actuator.py's labels section: what phi_a reads of each single fault at k = 1."""
    from phm_torch.assessment.label_check import label_visibility

    one = SineSweep(**{**vars(instantiate(shipped.sweep)), "rotor_positions": 1})
    found = label_visibility(params, one, instantiate(shipped.requirements))
    assert found["invisible"] == ["k3"]
    assert found["cases"]["k3"]["healthy"] and not found["cases"]["k4"]["healthy"]
    amp = found["sweep"]["amplitude"]
    assert params.backlash * (1 + 99 * found["k2_play_exceeds_sweep"]) == pytest.approx(amp, rel=1e-3)


def test_padded_sizes_waste_at_most_a_third_and_margins_rows_round_trip():
    from phm_torch.assessment import Margins

    sizes = [padded_size(n) for n in range(1, 5000)]
    assert sizes[:64] == [64] * 64 and padded_size(65) == 96 and padded_size(97) == 128 and padded_size(129) == 192
    assert all(s >= n and (s <= 64 or n > 0.66 * s) for n, s in zip(range(1, 5000), sizes, strict=True))
    assert len(set(sizes)) <= 2 * 7 + 1  # two sizes an octave
    m = Margins.from_stacked(torch.arange(20, dtype=torch.float64).reshape(4, 5))
    rows = torch.tensor([2, 0])
    assert torch.equal(m.take_rows(rows).stacked(), m.stacked()[rows])
    back = m.put_rows(rows, m.take_rows(torch.tensor([0, 2])))
    assert torch.equal(back.stacked()[[0, 2]], m.stacked()[[2, 0]]) and torch.equal(back.stacked()[1], m.stacked()[1])
    assert torch.equal(m.stacked()[0], torch.arange(5, dtype=torch.float64))  # m itself unchanged


def test_the_nominal_reading_is_measured_once_per_actuator_and_sweep(params, shipped, monkeypatch):
    """A second assessment function of the same actuator, sweep and device takes the nominal margins and the invisible
    faults of the first (no simulation); another actuator's, or another sweep's, measures its own."""
    from phm_torch.assessment import health

    monkeypatch.setattr(health, "_MEASURED", {})
    reads = []
    real = FrequencyResponse.read
    monkeypatch.setattr(FrequencyResponse, "read", lambda self, k: reads.append(k.shape[0]) or real(self, k))
    cheap = {"frequencies": (20.0, 40.0, 70.0, 110.0), "cycles": 3, "rotor_positions": 1}
    first = _assessment(params, shipped, **cheap)
    nominal, invisible = first.nominal.stacked(), first.invisible_faults()
    assert reads == [1, 4] and invisible == ["short_a"]
    again = _assessment(params, shipped, **cheap, compile=True)  # compiling changes no uncompiled reading
    assert torch.equal(again.nominal.stacked(), nominal) and again.invisible_faults() == invisible
    assert reads == [1, 4]
    geared = dataclasses.replace(params, gear_ratio=180.0)
    other = [_assessment(geared, shipped, **cheap), _assessment(params, shipped, **{**cheap, "cycles": 4})]
    assert all(math.isfinite(float(phi.nominal.bandwidth_hz[0])) for phi in other)
    assert reads == [1, 4, 1, 1]


@pytest.mark.slow  # the shipped sweep on the HF model, ~100 s
def test_the_lf_loop_reads_the_hf_loops_margins_as_the_position_gain_changes(params, shipped):
    """phi_a reads the LF model's loop; the HF model's (PWM inverter, three phases) reads the same margins at the
    nominal position gain and with k8 moving it by -30 % / +30 % / +50 %: HF gain margins ~0.25 dB lower (measured
    2026-11-29: 8.74 / 12.17 / 6.23 / 4.91 dB against 8.97 / 12.37 / 6.45 / 5.18), bandwidths within 1 %."""
    from phm_torch.simulator import EMASimulator

    sweep = SineSweep(**{**vars(instantiate(shipped.sweep)), "rotor_positions": 1})
    k = torch.tensor([params.nominal_faults] * 4, dtype=torch.float64)
    k[:, 7] = torch.tensor([0.5, 0.2, 0.8, 1.0], dtype=torch.float64)
    lf = FrequencyResponse(params, sweep)
    hf = FrequencyResponse(params, sweep, simulator=EMASimulator(lf.params, "hf"))
    a, b = (x.margins_of(x.read(k)).as_dict() for x in (lf, hf))
    assert torch.isnan(a["phase_margin_deg"][1]) and torch.isnan(b["phase_margin_deg"][1])  # below 0 dB everywhere
    assert (a["gain_margin_db"] - b["gain_margin_db"]).abs().max() < 0.5
    assert (a["gain_margin_db"][[0, 2, 3]] > b["gain_margin_db"][[0, 2, 3]]).all()  # the HF loop's extra lag
    keep = [0, 2, 3]
    assert (a["phase_margin_deg"][keep] - b["phase_margin_deg"][keep]).abs().max() < 1.5
    for name in ("bandwidth_hz", "phase_crossover_hz"):
        assert ((a[name] - b[name]).abs() / b[name]).max() < 0.03, name
    assert ((a["crossover_hz"][keep] - b["crossover_hz"][keep]).abs() / b["crossover_hz"][keep]).max() < 0.01


def test_an_ideal_position_sensor_is_the_limit_of_a_fast_one(params):
    """lvdt_time_constant may be 0 (an ideal sensor, docs/own_actuator.md): the linear loop then reads theta_u itself
    (it divided by zero before), and its margins are the limit of a sensor lag going to 0."""
    from phm_torch.assessment.design import SweepDesign

    ideal = SweepDesign.loop_figures(params.replace(lvdt_time_constant=0.0))
    fast = SweepDesign.loop_figures(params.replace(lvdt_time_constant=1e-7))
    slow = SweepDesign.loop_figures(params)  # 0.2 ms
    for name in ("crossover_hz", "phase_margin_deg", "gain_margin_db", "bandwidth_hz"):
        assert ideal[name] == pytest.approx(fast[name], rel=1e-3), name
    assert ideal["phase_margin_deg"] > slow["phase_margin_deg"]  # a lag only takes phase away


def test_a_fault_of_a_value_the_actuator_does_not_have_is_named_absent(params):
    """k = 1 scales the datasheet's value: with no play (or no friction) that fault does not exist on the actuator,
    and the derived sweep amplitude, sized from friction and play, has nothing to size it with both at 0."""
    from phm_torch.assessment.design import SweepDesign
    from phm_torch.assessment.label_check import absent_faults

    assert absent_faults(params) == {}
    assert absent_faults(params.replace(backlash=0.0)) == {"k2": "backlash"}
    frictionless = params.replace(static_friction=0.0, coulomb_friction=0.0)
    assert list(absent_faults(frictionless)) == ["k1"]
    assert SweepDesign().lower_amplitude(params.replace(backlash=0.0)) > 0  # friction alone sizes it
    with pytest.raises(ValueError, match="static_friction, coulomb_friction and backlash are all 0"):
        SweepDesign().lower_amplitude(frictionless.replace(backlash=0.0))
