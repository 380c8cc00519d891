"""Physical-effect library: registry, validation, exact zero at strength 0, physics of each effect.

Simulations are batched: one run carries one sample per effect, the effect enabled in that sample
only (its strength parameters are (B,) tensors, zero in the other samples), with sample 0 the
nominal actuator with every effect present at strength 0. The residual of sample i against sample 0
is then the signature of effect i alone on the same trajectory, which is compared with the physics
(expected sign, place and size). Low fidelity for the long runs, one short HF run for the per-phase
plant and the driven-pair current.
"""

from __future__ import annotations

import math
from types import SimpleNamespace
from typing import ClassVar

import pytest
import torch

from phm_torch.command import Chirp, Sine
from phm_torch.effects import EFFECTS, Effect, EffectContext, EffectParam, build_effects, register_effect
from phm_torch.effects.cogging_torque import cogging_periods
from phm_torch.params import load_actuator
from phm_torch.plant import build_plant
from phm_torch.simulator import EMASimulator

P = load_actuator()
BUILTIN = (
    "viscous_friction",
    "stribeck_friction",
    "cogging_torque",
    "transmission_compliance",
    "aero_hinge_load",
    "inverter_dead_time",
    "winding_temperature",
    "position_sensor_lag",
    "torque_constant_saturation",
    "torque_ripple",
)
LF_CASES = (None, *BUILTIN)  # row i enables LF_CASES[i] only; row 0: all at strength 0
HF_CASES = (None, "inverter_dead_time", "winding_temperature", "cogging_torque")
BARE_LF, BARE_HF = 0.25, 0.04  # [s] prefixes run without effects for the bit-identity checks
CHANNELS = ("position", "current", "speed", "motor_angle", "user_angle")


def nominal(batch: int) -> torch.Tensor:
    return torch.tensor([P.nominal_faults] * batch, dtype=torch.float64)


def one_at_a_time(cases) -> dict[str, dict[str, torch.Tensor]]:
    """Spec with every built-in effect; row i has only ``cases[i]`` at its default strength, the rest 0."""
    spec = {}
    for name in BUILTIN:
        cls = EFFECTS[name]
        spec[name] = {
            s: torch.tensor([cls.PARAMS[s].default if c == name else 0.0 for c in cases], dtype=torch.float64)
            for s in cls.STRENGTH
        }
    return spec


def record(sim: EMASimulator, batch: int, command, duration: float) -> dict[str, torch.Tensor]:
    """Run period by period and keep the internal states at the period starts, (B, n_periods) each.

    Keys: ``I`` signed current (LF: DC current, HF: driven-pair current) [A], ``u`` current-loop integrator
    [V], ``v`` voltage command applied during the period [V], ``wm``/``thm`` motor speed/angle, ``wu``/``thu``
    user speed/angle, ``lvdt``, ``cmd`` [rad]; and ``signals``: {channel: (B, n_samples - 1)}.
    """
    state = sim.init(nominal(batch))
    n = round(duration * P.pwm_frequency)
    cmd = command(torch.arange(n, dtype=torch.float64) * sim.period)  # the instants of EMASimulator.run
    keys = ("I", "u", "v", "wm", "thm", "wu", "thu", "lvdt", "cmd")
    rec: dict[str, list] = {k: [] for k in keys}
    samples = []
    for k in range(n):
        m, plant = state.mech, state.plant
        for key, val in zip(
            keys,
            (
                sim.motor.feedback_current(state.elec, m.theta_m, plant),
                state.ctrl.current_int,
                state.ctrl.duty * plant.supply_voltage,
                m.omega_m,
                m.theta_m,
                m.omega_u,
                m.theta_u,
                state.lvdt,
                cmd[k].expand(batch),
            ),
        ):
            rec[key].append(val)
        state, s = sim.step(state, cmd[k])
        samples.extend(s)
    out = {k: torch.stack(v, -1) for k, v in rec.items()}
    out["signals"] = {c: torch.stack([s[c] for s in samples], -1) for c in CHANNELS}
    return out


def lstsq(y: torch.Tensor, *cols: torch.Tensor) -> torch.Tensor:
    """Least-squares coefficients of y on the given regressors (a column of ones is not added)."""
    a = torch.stack([torch.broadcast_to(c, y.shape) for c in cols], -1)
    return torch.linalg.lstsq(a, y.unsqueeze(-1)).solution.squeeze(-1)


@pytest.fixture(scope="module")
def lf():
    """0.5 s test chirp, LF, one effect per row; plus the same run without any effect."""
    sim = EMASimulator(P, "lf", effects=one_at_a_time(LF_CASES))
    rec = record(sim, len(LF_CASES), Chirp(), Chirp().duration)
    rec["bare"] = EMASimulator(P, "lf").run(nominal(len(LF_CASES)), Chirp(), BARE_LF)  # a prefix suffices
    rec["row"] = {c: i for i, c in enumerate(LF_CASES)}
    rec["steady"] = slice(int(0.05 * P.pwm_frequency), None)  # skip the start-up transient
    return rec


@pytest.fixture(scope="module")
def hf():
    """0.1 s of a 10 Hz sine (motor speed up to ~60 rad/s), HF, one effect per row; plus a bare run."""
    cmd = Sine(Chirp().amplitude, 10.0, 0.1)
    sim = EMASimulator(P, "hf", effects=one_at_a_time(HF_CASES))
    rec = record(sim, len(HF_CASES), cmd, cmd.duration)
    rec["bare"] = record(EMASimulator(P, "hf"), len(HF_CASES), cmd, BARE_HF)
    rec["row"] = {c: i for i, c in enumerate(HF_CASES)}
    rec["steady"] = slice(int(0.02 * P.pwm_frequency), None)
    return rec


def identify(rec, row: int) -> torch.Tensor:
    """(R_eq [ohm], k_eq [V s/rad], L_eq [H]) by least squares on v = R_eq I + k_eq w + L_eq dI/dt.

    v is the voltage command applied over each control period, I and w the period means (trapezoid of
    the period-start values) of the signed current and of the motor speed, after the start-up.
    """
    cur, w, v = rec["I"][row], rec["wm"][row], rec["v"][row]
    ss = rec["steady"]

    def mid(x):
        return 0.5 * (x[:-1] + x[1:])

    return lstsq(v[:-1][ss], mid(cur)[ss], mid(w)[ss], (torch.diff(cur) * P.pwm_frequency)[ss])


def delta(rec, name: str, key: str = "I") -> torch.Tensor:
    return rec[key][rec["row"][name]] - rec[key][0]


def torque_constant() -> float:
    """Torque of the two conducting phases per ampere, 2 k_e [N m/A] (ema_reference.md §1)."""
    return 2.0 * P.back_emf_constant


# ---- declarations, registry, validation ---------------------------------------------------------
def test_registry_has_every_builtin_with_declarations():
    for name in BUILTIN:
        cls = EFFECTS[name]
        assert cls.name == name and issubclass(cls, Effect)
        assert cls.STRENGTH and set(cls.STRENGTH) <= set(cls.PARAMS)
        assert len(cls.explains) > 20
        for key, spec in cls.PARAMS.items():
            assert isinstance(spec, EffectParam) and spec.unit and spec.description and spec.scale > 0, key
            assert spec.minimum is None or spec.default >= spec.minimum, key
    built = build_effects({name: {} for name in BUILTIN})  # `+effects.NAME={}`: the defaults
    assert [e.name for e in built] == list(BUILTIN)
    for e in built:
        assert all(float(e[s]) != 0.0 for s in e.STRENGTH), e


@pytest.mark.parametrize(
    "spec, fragment",
    [
        ({"no_such_effect": {}}, "no_such_effect"),
        ({"cogging_torque": {"amplitud": 1e-3}}, "amplitud"),
        ({"viscous_friction": {"coefficient": -1e-4}}, "effects.viscous_friction.coefficient"),
        ({"inverter_dead_time": {"dead_time": -1e-6}}, "effects.inverter_dead_time.dead_time"),
        ({"stribeck_friction": {"velocity": 0.0}}, "effects.stribeck_friction.velocity"),
        ({"winding_temperature": {"temperature_rise": float("nan")}}, "effects.winding_temperature.temperature_rise"),
        ({"aero_hinge_load": {"bias": "1 N m"}}, "effects.aero_hinge_load.bias"),
    ],
)
def test_bad_specs_raise_value_error_naming_the_field(spec, fragment):
    with pytest.raises(ValueError, match=fragment.replace(".", r"\.")):
        EMASimulator(P, "lf", effects=spec)


def test_signed_parameters_accept_negative_values():
    e = build_effects(
        {
            "aero_hinge_load": {"stiffness": -500.0, "bias": -2.0},
            "cogging_torque": {"phase": -1.0},
            "winding_temperature": {"temperature_rise": -20.0},
        }
    )
    assert float(e[0]["bias"]) == -2.0 and float(e[2]["temperature_rise"]) == -20.0


def test_user_defined_effect_in_a_few_lines():
    @register_effect
    class ConstantDrag(Effect):
        name = "test_constant_drag"
        PARAMS: ClassVar[dict[str, EffectParam]] = {"torque": EffectParam(2e-3, "N m", "signed drag torque", None)}
        STRENGTH = ("torque",)
        explains = "constant current offset"

        def motor_torque(self, ctx: EffectContext) -> torch.Tensor:
            return -self.values["torque"]

    try:
        sims = [EMASimulator(P, "lf", effects={"test_constant_drag": v}) for v in ({"torque": 0.0}, {})]
        runs = [s.run(nominal(1), Chirp(), 0.05) for s in sims]
        bare = EMASimulator(P, "lf").run(nominal(1), Chirp(), 0.05)
        assert torch.equal(runs[0]["current"], bare["current"])
        assert (runs[1]["current"] - bare["current"]).abs().max() > 0.01  # 2e-3 N m / 0.08 N m/A = 25 mA
    finally:
        EFFECTS.pop("test_constant_drag", None)
    assert "test_constant_drag" not in EFFECTS


# ---- exact zero -----------------------------------------------------------------------------------
def test_zero_strength_is_bit_identical_lf(lf):
    for c in CHANNELS:
        bare = lf["bare"][c][0, :-1]
        assert torch.equal(lf["signals"][c][0, : bare.numel()], bare), c


def test_zero_strength_is_bit_identical_hf(hf):
    bare = hf["bare"]
    for key in ("I", "u", "v", "wm", "thm", "thu", "lvdt"):
        assert torch.equal(hf[key][0, : bare[key].shape[-1]], bare[key][0]), key
    for c in CHANNELS:
        assert torch.equal(hf["signals"][c][0, : bare["signals"][c].shape[-1]], bare["signals"][c][0]), c


def test_every_default_is_visible(lf):
    """Each effect at its default changes the current or the position by > 0.2 % of the nominal range."""
    sig = lf["signals"]
    for name in BUILTIN:
        i = lf["row"][name]
        nrmse = [
            ((sig[c][i] - sig[c][0]).pow(2).mean().sqrt() / (sig[c][0].max() - sig[c][0].min())).item()
            for c in ("current", "position")
        ]
        assert max(nrmse) > 2e-3, (name, nrmse)


def test_typical_magnitudes_follow_the_actuator_size():
    """The workbench normalises, bounds and probes an effect parameter by its typical magnitude on the actuator
    being fitted: on the default datasheet that is the effect's declared default, on the 270 V rudder (5 x the
    peak motor torque, 10 x the hinge moment) torques and damping scale with it, absolute ones do not."""
    rudder = load_actuator("ema_hvdc_rudder")
    torque_ratio = (rudder.back_emf_constant * rudder.current_limit) / (P.back_emf_constant * P.current_limit)
    assert torque_ratio == pytest.approx(5.0)
    for name in BUILTIN:
        for key, spec in EFFECTS[name].PARAMS.items():
            if (key in EFFECTS[name].STRENGTH or spec.per) and name != "transmission_compliance":
                assert spec.scale_for(P) == pytest.approx(abs(spec.default), rel=1e-12), (name, key)
    compliance = EFFECTS["transmission_compliance"].PARAMS["compliance"]
    assert compliance.scale_for(P) == pytest.approx(4 / P.output_stiffness)  # probed at 0.4 / K_t
    assert compliance.scale_for(rudder) == pytest.approx(4 / rudder.output_stiffness)
    assert EFFECTS["cogging_torque"].PARAMS["amplitude"].scale_for(rudder) == pytest.approx(5 * 4e-3)
    hinge = EFFECTS["aero_hinge_load"].PARAMS["bias"]
    assert hinge.scale_for(rudder) == pytest.approx(
        hinge.scale_for(P) * torque_ratio * rudder.gear_ratio / P.gear_ratio
    )
    lag = EFFECTS["position_sensor_lag"].PARAMS["time_constant"]
    assert not lag.per and lag.scale_for(rudder) == lag.scale_for(P) == lag.scale
    with pytest.raises(ValueError, match="unknown actuator unit 'stall_torque'"):
        EffectParam(0.0, "N m", "x", per="stall_torque")
    with pytest.raises(ValueError, match="'peak_user_torque' must be positive"):  # a datasheet refuses it first
        hinge.scale_for(SimpleNamespace(back_emf_constant=0.0, current_limit=15.0, gear_ratio=200.0))


def test_shape_parameters_sized_by_the_actuator_default_to_its_size_and_grids_are_multiples():
    """An effect added without its sized shape parameters takes the actuator's size (the rudder's Stribeck
    velocity: its 600 rad/s speed limit / 60, not the reference's 5 rad/s), in the simulator, the apps and the
    workbench alike; strengths keep their declared defaults; the workbench's probe grid lists sized parameters
    in multiples of that size (the shipped Stribeck grid: 2, 5, 15 rad/s on the reference, 4, 10, 30 on the
    rudder)."""
    from phm_torch.apps.common import effects as app_effects
    from phm_torch.workbench.candidates import ScoreSettings, directions
    from phm_torch.workbench.parameters import effect_defaults

    rudder = load_actuator("ema_hvdc_rudder")
    spec = {"stribeck_friction": {}, "torque_constant_saturation": {"current_scale": 7.0}}
    for built in (build_effects(spec, rudder), app_effects(spec, rudder), EMASimulator(rudder, "lf", spec).effects):
        by_name = {e.name: e for e in built}
        assert float(by_name["stribeck_friction"]["velocity"]) == pytest.approx(rudder.speed_limit / 60)
        assert (
            float(by_name["stribeck_friction"]["amplitude"]) == EFFECTS["stribeck_friction"].PARAMS["amplitude"].default
        )
        assert float(by_name["torque_constant_saturation"]["current_scale"]) == 7.0  # given: kept
    assert float(build_effects(spec)[0]["velocity"]) == EFFECTS["stribeck_friction"].PARAMS["velocity"].default
    for params in (P, rudder):
        assert effect_defaults("inverter_dead_time", None, params)["current_scale"] == pytest.approx(
            params.current_limit / 150
        )
    assert effect_defaults("stribeck_friction", None, P) == effect_defaults("stribeck_friction")  # the reference
    grid = ScoreSettings(grid={"stribeck_friction": {"velocity": [0.4, 1.0, 3.0]}, "cogging_torque": {"phase": [1.0]}})
    for params, expect in ((P, [2.0, 5.0, 15.0]), (rudder, [4.0, 10.0, 30.0])):
        dirs = directions(["stribeck_friction", "cogging_torque"], grid, params)
        assert [d.values["velocity"] for d in dirs if d.effect == "stribeck_friction"] == pytest.approx(expect)
        assert [d.values["phase"] for d in dirs if d.effect == "cogging_torque"] == [1.0]  # not sized: its unit


def test_gradients_of_strengths_at_zero_match_finite_differences():
    """Score test: d(loss)/d(strength) at 0 by autograd, every strength of every effect in one short run.

    Row 0 has every strength at 0 (autograd there); row r > 0 moves one strength by 1e-5 of its scale
    (one-sided finite difference of the same loss). The step is small because the loss is only piecewise
    smooth: a larger one (e.g. 1e-3 N m of hinge bias) can flip a stick or backlash-contact event.
    """
    leaves = [(n, k) for n in BUILTIN for k in EFFECTS[n].STRENGTH]
    b = 1 + len(leaves)
    zeros = {leaf: torch.zeros(b, dtype=torch.float64, requires_grad=True) for leaf in leaves}
    steps = {leaf: 1e-5 * EFFECTS[leaf[0]].PARAMS[leaf[1]].scale_for(P) for leaf in leaves}
    spec: dict[str, dict[str, torch.Tensor]] = {n: {} for n in BUILTIN}
    for r, leaf in enumerate(leaves, start=1):
        bump = torch.zeros(b, dtype=torch.float64)
        bump[r] = steps[leaf]
        spec[leaf[0]][leaf[1]] = zeros[leaf] + bump
    s = EMASimulator(P, "lf", effects=spec).run(nominal(b), Chirp(), 0.08)
    loss = s["current"].pow(2).mean(-1) + ((s["position"] - s["command"]) / 1e-3).pow(2).mean(-1)  # (B,)
    grads = torch.autograd.grad(loss[0], [zeros[leaf] for leaf in leaves])
    for r, (leaf, g) in enumerate(zip(leaves, grads), start=1):
        assert torch.isfinite(g).all() and (g[1:] == 0).all(), leaf  # rows are independent
        fd = (loss[r] - loss[0]).detach() / steps[leaf]
        assert g[0] != 0, leaf
        assert g[0].item() == pytest.approx(fd.item(), rel=0.01), leaf


# ---- static effects on the plant --------------------------------------------------------------------
def test_modify_plant_static_effects():
    k = torch.tensor([P.nominal_faults, [0, 0, 0.5, 0, 0, 0, 0.5, 0.5]], dtype=torch.float64)
    base = build_plant(P, k)
    dt = torch.tensor([0.0, 50.0], dtype=torch.float64)
    comp = torch.tensor([2e-5, 0.0], dtype=torch.float64)
    effects = build_effects(
        {
            "winding_temperature": {"temperature_rise": dt},
            "transmission_compliance": {"compliance": comp},
            "position_sensor_lag": {"time_constant": 5e-4},
        }
    )
    plant = build_plant(P, k)
    for e in effects:
        plant = e.modify_plant(plant)
    r, m = 1 + 3.93e-3 * dt, 1 - 1.2e-3 * dt
    assert torch.allclose(plant.phase_resistance, base.phase_resistance * r)
    assert torch.allclose(plant.resistance, base.resistance * r[:, None])  # per-phase, shorted phase kept
    assert torch.allclose(plant.back_emf_constant, base.back_emf_constant * m)
    assert torch.allclose(plant.emf, base.emf * m[:, None])
    assert torch.equal(plant.inductance, base.inductance)
    assert plant.resistance[1, 0] > base.resistance[1, 0] and plant.emf[1, 0] < base.emf[1, 0]
    # series springs: 1/K_eff = 1/K_t + C; lower stiffness, unchanged at C = 0
    assert torch.allclose(1 / plant.output_stiffness, 1 / base.output_stiffness + comp)
    assert (
        plant.output_stiffness[0] < base.output_stiffness[0] and plant.output_stiffness[1] == base.output_stiffness[1]
    )
    assert torch.allclose(plant.lvdt_time_constant, base.lvdt_time_constant + 5e-4)


def test_cogging_period_from_the_datasheet():
    plant = build_plant(P, nominal(1))
    assert cogging_periods(plant) == P.stator_slots  # 24 slots, 8 poles: one period per slot pitch
    other = build_plant(P.replace(stator_slots=9, pole_pairs=3), nominal(1))
    assert cogging_periods(other) == 18


# ---- physics on the LF chirp ---------------------------------------------------------------------------
def test_viscous_friction_current_proportional_to_speed(lf):
    c = EFFECTS["viscous_friction"].PARAMS["coefficient"].default
    ss = lf["steady"]
    d_i, w = delta(lf, "viscous_friction")[ss], lf["wm"][0][ss]
    slope = lstsq(d_i, w)[0]
    assert slope == pytest.approx(c / torque_constant(), rel=0.15)  # dI = c w / k_t
    fast, slow = w.abs() > 40, w.abs() < 5
    assert d_i[fast].abs().mean() > 10 * d_i[slow].abs().mean()  # at peak speed, not at reversals


def test_stribeck_friction_current_at_low_speed(lf):
    a = EFFECTS["stribeck_friction"].PARAMS["amplitude"].default
    ws = EFFECTS["stribeck_friction"].PARAMS["velocity"].default
    ss = lf["steady"]
    d_i, w = delta(lf, "stribeck_friction")[ss], lf["wm"][0][ss]
    slow, fast = w.abs() < ws, w.abs() > 4 * ws
    assert d_i[slow].abs().mean() > 10 * d_i[fast].abs().mean()  # around velocity reversals
    shape = torch.tanh(w / (0.1 * ws)) * torch.exp(-((w / ws) ** 2))
    assert lstsq(d_i, shape)[0] == pytest.approx(a / torque_constant(), rel=0.4)  # against the motion


def test_cogging_current_at_the_slot_harmonic(lf):
    a = EFFECTS["cogging_torque"].PARAMS["amplitude"].default
    z = cogging_periods(build_plant(P, nominal(1)))
    ss = lf["steady"]
    i = lf["row"]["cogging_torque"]
    d_i, th = delta(lf, "cogging_torque")[ss], lf["thm"][i][ss]
    orders = (z - 7, z, z + 7, 2 * z)
    cols = [f(n * th) for n in orders for f in (torch.sin, torch.cos)]
    coef = lstsq(d_i, *cols, torch.ones_like(th)).reshape(-1)[:-1].reshape(len(orders), 2)
    amp = coef.norm(dim=-1)
    # the motor must supply +A sin(Z theta): in phase with sin, partly rejected by the speed loop
    assert 0.5 * a / torque_constant() < coef[1, 0] < 1.2 * a / torque_constant()
    assert abs(coef[1, 1]) < 0.3 * coef[1, 0]
    assert amp[1] > 3 * torch.cat([amp[:1], amp[2:]]).max()


def test_transmission_compliance_increases_deflection(lf):
    c = EFFECTS["transmission_compliance"].PARAMS["compliance"].default
    i = lf["row"]["transmission_compliance"]

    def deflection(row):
        return (lf["thm"][row] / P.gear_ratio - lf["thu"][row]).pow(2).mean().sqrt()

    ratio = deflection(i) / deflection(0)
    assert ratio == pytest.approx(1 + P.output_stiffness * c, rel=0.1)  # same torque, softer spring


def test_aero_hinge_load_current_in_phase_with_position(lf):
    spec = EFFECTS["aero_hinge_load"].PARAMS
    ss = lf["steady"]
    d_i, th = delta(lf, "aero_hinge_load")[ss], lf["thu"][lf["row"]["aero_hinge_load"]][ss]
    slope, offset = lstsq(d_i, th, torch.ones_like(th))
    scale = P.gear_ratio * torque_constant()
    assert slope == pytest.approx(spec["stiffness"].default / scale, rel=0.1)
    assert offset == pytest.approx(spec["bias"].default / scale, rel=0.1)


def test_inverter_dead_time_costs_voltage_against_the_current(lf):
    spec = EFFECTS["inverter_dead_time"].PARAMS
    ss = lf["steady"]
    i = lf["row"]["inverter_dead_time"]
    expected = 2 * P.supply_voltage * spec["dead_time"].default * P.pwm_frequency
    cur = lf["I"][i][ss]
    # the current loop (mostly its integrator) commands the lost volt-seconds: 2 V_dc t_d f_pwm in the
    # current's direction, so the current itself barely changes
    for key, tol in (("v", 0.05), ("u", 0.1)):
        gain, offset = lstsq(
            delta(lf, "inverter_dead_time", key)[ss],
            torch.tanh(cur / spec["current_scale"].default),
            torch.ones_like(cur),
        )
        assert gain == pytest.approx(expected, rel=tol), key
        assert abs(offset) < 0.05 * gain, key


def test_winding_temperature_more_current_and_voltage(lf):
    spec = EFFECTS["winding_temperature"].PARAMS
    dt = spec["temperature_rise"].default
    ss = lf["steady"]
    i = lf["row"]["winding_temperature"]
    # weaker magnets: more current for the same torque
    slope = lstsq(lf["I"][i][ss], lf["I"][0][ss])[0]
    assert slope == pytest.approx(1 / (1 + spec["alpha_magnet"].default * dt), rel=0.01)
    # the voltage applied over each period gives R_eq and k_eq: more resistance, less back-EMF
    hot, cold = identify(lf, i), identify(lf, 0)
    assert cold[0] == pytest.approx(2 * P.phase_resistance, rel=0.1)
    assert cold[1] == pytest.approx(torque_constant(), rel=0.05)
    assert hot[0] / cold[0] == pytest.approx(1 + spec["alpha_copper"].default * dt, rel=0.05)
    assert hot[1] / cold[1] == pytest.approx(1 + spec["alpha_magnet"].default * dt, abs=0.01)


def test_position_sensor_lag_delays_the_measurement(lf):
    tau = EFFECTS["position_sensor_lag"].PARAMS["time_constant"].default
    ss = lf["steady"]
    i = lf["row"]["position_sensor_lag"]

    def lag(row):  # first-order sensor: theta_u - lvdt = tau_total * d(lvdt)/dt
        gap, lvdt = lf["thu"][row] - lf["lvdt"][row], lf["lvdt"][row]
        return lstsq((0.5 * (gap[:-1] + gap[1:]))[ss], (torch.diff(lvdt) * P.pwm_frequency)[ss])[0]

    h = P.control_period / 2  # the LF substep: the sensor update reads the end-of-substep angle (-h/2 of lag)
    assert lag(0) == pytest.approx(P.lvdt_time_constant, abs=h)
    assert lag(i) - lag(0) == pytest.approx(tau, rel=0.02)
    # last chirp cycle (~14 Hz): the reading lags the surface by atan(w tau); the loop, closed on the late
    # reading, drives the surface ahead, while the measured position lags the command more, with more
    # resonant peaking (less phase margin) and a larger tracking error
    chirp = Chirp()
    rate = (chirp.f_end - chirp.f_start) / chirp.duration
    t = torch.arange(lf["cmd"].shape[-1], dtype=torch.float64) * P.control_period
    last = t > chirp.duration - 1 / chirp.f_end
    ref = torch.exp(-2j * math.pi * (chirp.f_start * t[last] + 0.5 * rate * t[last] ** 2))  # conjugate phasor

    def response(x):  # complex gain against the command over the last cycle
        return (x[last] * ref).sum() / (lf["cmd"][0][last] * ref).sum()

    f_last = chirp.f_end - 0.5 * rate / chirp.f_end  # mean frequency of the last cycle

    def sensor_phase(row):  # phase of the surface relative to the reading
        return torch.angle(response(lf["thu"][row]) / response(lf["lvdt"][row]))

    extra = math.atan(2 * math.pi * f_last * lag(i)) - math.atan(2 * math.pi * f_last * lag(0))
    assert sensor_phase(i) - sensor_phase(0) == pytest.approx(extra, rel=0.25)
    assert torch.angle(response(lf["lvdt"][i])) < torch.angle(response(lf["lvdt"][0])) - math.radians(0.5)
    assert response(lf["lvdt"][i]).abs() > response(lf["lvdt"][0]).abs() + 0.01
    err = [(lf["lvdt"][r] - lf["cmd"][r]).pow(2).mean().sqrt() for r in (0, i)]
    assert err[1] > 1.01 * err[0]


def test_torque_constant_saturation_needs_more_current_at_high_current(lf):
    spec = EFFECTS["torque_constant_saturation"].PARAMS
    a, i_s = spec["coefficient"].default, spec["current_scale"].default
    i = lf["row"]["torque_constant_saturation"]
    cur0, cur = lf["I"][0], lf["I"][i]
    big, small = cur0.abs() > 1.5, cur0.abs() < 0.3
    excess = (cur[big] / cur0[big]).mean() - 1
    assert excess == pytest.approx(a * (cur[big] / i_s).pow(2).mean().item(), rel=0.1)  # k(I) I = k I0
    assert (cur[big] / cur0[big]).mean() - 1 > 10 * (
        (cur - cur0)[small].abs() / cur0[small].abs().clamp(min=0.1)
    ).mean()


# ---- HF: per-phase plant and driven-pair current --------------------------------------------------------
def test_hf_dead_time_temperature_and_cogging(hf):
    ss = hf["steady"]
    dead = EFFECTS["inverter_dead_time"].PARAMS
    i = hf["row"]["inverter_dead_time"]
    d_v, cur = delta(hf, "inverter_dead_time", "v")[ss], hf["I"][i][ss]
    gain = lstsq(d_v, torch.tanh(cur / dead["current_scale"].default), torch.ones_like(cur))[0]
    assert gain == pytest.approx(2 * P.supply_voltage * dead["dead_time"].default * P.pwm_frequency, rel=0.1)

    temp = EFFECTS["winding_temperature"].PARAMS
    i = hf["row"]["winding_temperature"]
    dt = temp["temperature_rise"].default
    slope = lstsq(hf["I"][i][ss], hf["I"][0][ss])[0]
    assert slope == pytest.approx(1 / (1 + temp["alpha_magnet"].default * dt), rel=0.02)
    ratio = identify(hf, i) / identify(hf, 0)  # the per-phase R and k_e changed
    assert ratio[0] == pytest.approx(1 + temp["alpha_copper"].default * dt, rel=0.03)
    assert ratio[1] == pytest.approx(1 + temp["alpha_magnet"].default * dt, abs=0.01)

    a = EFFECTS["cogging_torque"].PARAMS["amplitude"].default
    z = cogging_periods(build_plant(P, nominal(1)))
    i = hf["row"]["cogging_torque"]
    th = hf["thm"][i][ss]
    coef = lstsq(delta(hf, "cogging_torque")[ss], torch.sin(z * th), torch.cos(z * th), torch.ones_like(th))
    assert 0.4 * a / torque_constant() < coef[0] < 1.2 * a / torque_constant()
