"""phm-predict's record (phm_torch/online/diagnosis.py): an RUL bound beyond the pipeline's horizon is unknown
(null, ``rul_censored``), never the horizon written as a number; the components the test command does not
identify are named (``k_not_identified``)."""

from __future__ import annotations

import math
from pathlib import Path

import pytest
import torch

from phm_torch.faults import FAULT_NAMES
from phm_torch.online.corruptions import Record
from phm_torch.online.diagnosis import censor, diagnose, not_identified
from phm_torch.online.input_contract import InputContract
from phm_torch.online.loaded import TorchScriptPipeline
from phm_torch.surrogates.metrics import IDENTIFIED_R2, fdi_identifiability

PIPELINE = Path(__file__).resolve().parents[1] / "pretrained" / "online_surrogates_best.pt"


def test_censor_nulls_every_bound_at_or_beyond_the_horizon():
    assert censor([0.0, 1200.0, 20000.0], 20000.0) == ({"p5": 0.0, "p50": 1200.0, "p95": None}, True)
    assert censor([10.0, 20.0, 30.0], 20000.0) == ({"p5": 10.0, "p50": 20.0, "p95": 30.0}, False)
    assert censor([math.nan, 5.0, 25000.0], 20000.0)[0] == {"p5": None, "p50": 5.0, "p95": None}
    assert censor([1.0, 2.0, 3.0], math.inf)[1] is False  # a file without its horizon: nothing censored


def test_identifiability_is_r2_per_component():
    g = torch.Generator().manual_seed(0)
    k = torch.rand(2000, 8, generator=g, dtype=torch.float64)
    k_hat = k.clone()
    k_hat[:, 1] = k[:, 1] + 0.1 * torch.randn(2000, generator=g, dtype=torch.float64)  # var 1/12: R^2 0.88
    k_hat[:, 5] = 0.5  # the prior: R^2 ~0
    k_hat[:, 6] = 1.0 - k[:, 6]  # anti-correlated: -3
    r2 = fdi_identifiability(k_hat, k)
    assert r2[0] == pytest.approx(1.0) and r2[1] == pytest.approx(1 - 0.01 * 12, abs=0.03)
    assert abs(r2[5]) < 0.01 and r2[6] == pytest.approx(-3.0, abs=0.1)
    flat = k.clone()
    flat[:, 7] = 0.5
    assert math.isnan(fdi_identifiability(flat, flat)[7])  # a component that never varies: unknown
    metadata = {"identifiability": dict(zip(FAULT_NAMES, r2))}
    assert not_identified(metadata) == [FAULT_NAMES[5], FAULT_NAMES[6]]
    assert not_identified({}) == [] and IDENTIFIED_R2 == 0.25


def test_phm_evaluate_names_the_unidentified_components_and_how_to_tell_why(caplog):
    """A component read at its prior: the warning says which, and points at the probe that tells a fault the command
    does not excite from one the pipeline's configuration does not read (docs/own_actuator.md)."""
    from phm_torch.pipelines.evaluate.calibration import identifiability

    g = torch.Generator().manual_seed(0)
    k = torch.rand(500, 8, generator=g, dtype=torch.float64)
    k_hat = k.clone()
    k_hat[:, 5] = 0.5
    with caplog.at_level("WARNING"):
        r2 = identifiability(k_hat, k, torch.zeros(500, dtype=torch.bool))
    assert r2["eccentricity"] < 0.25 and r2["backlash"] == pytest.approx(1.0)
    assert "does not identify eccentricity" in caplog.text and "scripts/fdi_capacity_probe.py" in caplog.text


@pytest.mark.torchscript
def test_the_predict_record_names_unidentified_components_and_censors_a_bound_past_the_horizon():
    torch.set_num_threads(1)
    module = torch.jit.load(str(PIPELINE))
    model = TorchScriptPipeline(module, {"identifiability": {"eccentricity": 0.11, "dry_friction": 0.8}})
    nominal = module.nominal_record.double()
    t = torch.arange(nominal.numel(), dtype=torch.float64) / 20000.0
    record = diagnose(model, Record(t, None, None, nominal.clone()), InputContract.of(model, {}, None))
    assert record["k_not_identified"] == ["eccentricity"]
    raw = model.run(nominal.unsqueeze(0)).rul[0].tolist()
    assert raw[2] >= model.horizon_hours  # the nominal actuator outlives the horizon at 95 %
    assert record["rul_censored"] and record["rul_hours"]["p95"] is None
    expected_p50 = None if raw[1] >= model.horizon_hours else pytest.approx(raw[1])
    assert record["rul_hours"]["p50"] == expected_p50


def test_tracking_nrmse_is_the_library_nrmse_and_undefined_for_a_constant_command():
    from phm_torch.metrics import nrmse
    from phm_torch.online.input_contract import tracking_nrmse, tracking_range

    t = torch.linspace(0, 1, 501, dtype=torch.float64)
    cmd = 0.01 * torch.sin(6.0 * t)
    pos = 0.9 * cmd
    assert tracking_nrmse(cmd, pos) == pytest.approx(float(nrmse(pos, cmd)))
    assert tracking_range(cmd, torch.stack([pos, cmd])) == pytest.approx([0.0, float(nrmse(pos, cmd))])
    assert math.isnan(tracking_nrmse(torch.zeros(501, dtype=torch.float64), pos))


def test_a_reversed_current_is_found_by_its_mean_and_shape_together():
    """A probe the wrong way round is read as -current; a record whose mean alone has the other sign, or one reversed
    in time (its mean keeps its sign), is not: those are the ``sign`` check's and the consistency check's."""
    from phm_torch.online.record_corrections import correct_polarity, polarity_reversal

    t = torch.arange(2001, dtype=torch.float64) / 20000.0
    nominal = 0.3 + torch.sin(2 * math.pi * 15 * t)  # a mean of the nominal's sign, the shape of a chirp's current
    assert polarity_reversal(nominal, nominal) is None and polarity_reversal(nominal, None) is None
    assert polarity_reversal(-nominal, nominal) == pytest.approx(-1.0)
    faulty = 0.5 * nominal + 0.4 * torch.sin(2 * math.pi * 40 * t)  # reshaped by a fault, still the nominal's sign
    assert polarity_reversal(-faulty, nominal) < 0.0 and polarity_reversal(faulty, nominal) is None
    assert polarity_reversal(nominal - 0.6, nominal) is None  # the other mean, the nominal shape: not a reversed probe
    assert polarity_reversal(nominal.flip(0), nominal) is None  # reversed in time
    assert polarity_reversal(-nominal[:-1], nominal) is None  # another length: nothing to compare
    holed = -nominal.clone()
    holed[::7] = float("nan")  # missing samples: still read
    record, corr = correct_polarity(Record(t, t, t, holed), nominal)
    assert corr < -0.99 and torch.equal(record.current.nan_to_num(), (-holed).nan_to_num())
    assert record.command is not None and torch.equal(record.position, t)  # only the current is turned round


@pytest.mark.torchscript
def test_a_bench_with_its_probe_turned_round_reads_as_one_the_right_way(compose, tmp_path):
    """phm-predict with a baseline: the bench's healthy record and the measurement both reversed give the answer of
    both the right way round, without a flag."""
    from phm_torch.apps.predict import predict

    module = torch.jit.load(str(PIPELINE))
    nominal = module.nominal_record.double()
    t = torch.arange(nominal.numel(), dtype=torch.float64) / 20000.0
    g = torch.Generator().manual_seed(1)
    bench = nominal * 1.01 + 0.002 * torch.randn(nominal.numel(), generator=g, dtype=torch.float64)
    measured = nominal * 1.01 + 0.002 * torch.randn(nominal.numel(), generator=g, dtype=torch.float64)

    def csv(name, x):
        path = tmp_path / name
        path.write_text("time,current\n" + "\n".join(f"{a!r},{b!r}" for a, b in zip(t.tolist(), x.tolist())) + "\n")
        return path

    answers = []
    for sign in (1.0, -1.0):
        base, rec = csv(f"base{sign}.csv", sign * bench), csv(f"rec{sign}.csv", sign * measured)
        _, out = predict(compose("predict", [f"pipeline={PIPELINE}", f"measurements=[{rec}]", f"baseline=[{base}]"]))
        answers.append(out["records"][0])
    right, turned = answers
    assert not turned["out_of_distribution"] and turned["current_reversed"] and not right["current_reversed"]
    assert turned["k_hat"] == pytest.approx(right["k_hat"]) and turned["healthy"] == right["healthy"]


def test_a_reversed_position_sensor_is_read_the_right_way_round_and_a_stalled_one_is_not():
    from phm_torch.online.record_corrections import correct_position_polarity

    t = torch.arange(2001, dtype=torch.float64) / 20000.0
    cmd = 5e-3 * torch.sin(2 * math.pi * 10 * t)
    follows = 0.95 * 5e-3 * torch.sin(2 * math.pi * 10 * t - 0.2)
    record, corr = correct_position_polarity(Record(t, cmd, -follows, torch.ones_like(t)))
    assert corr < -0.9 and torch.equal(record.position, follows) and torch.equal(record.current, torch.ones_like(t))
    assert correct_position_polarity(Record(t, cmd, follows, torch.ones_like(t)))[1] is None
    stalled = 1e-5 * torch.sin(2 * math.pi * 37 * t)  # uncorrelated with its command: left for the tracking check
    assert correct_position_polarity(Record(t, cmd, stalled, torch.ones_like(t)))[1] is None
    assert correct_position_polarity(Record(t, cmd, torch.zeros_like(t), torch.ones_like(t)))[1] is None  # dead
    assert correct_position_polarity(Record(t, None, -follows, torch.ones_like(t)))[1] is None  # nothing to compare
    aligned_cmd, aligned_pos = cmd.clone(), (-follows).clone()
    aligned_cmd[-40:], aligned_pos[-40:] = float("nan"), float("nan")  # moved back onto its trigger: its end missing
    record, corr = correct_position_polarity(Record(t, aligned_cmd, aligned_pos, torch.ones_like(t)))
    assert corr < -0.9 and torch.equal(record.position[:-40], follows[:-40])


def test_a_refused_record_far_off_the_nominal_scale_says_so():
    from phm_torch.online.diagnosis import scale_message

    t = torch.arange(2001, dtype=torch.float64) / 20000.0
    nominal = 0.3 + torch.sin(2 * math.pi * 15 * t)
    assert scale_message(nominal * 3.0, nominal) is None and scale_message(nominal / 3.0, nominal) is None
    assert "(the current written in mA? name the column 'current [mA]')" in scale_message(1000.0 * nominal, nominal)
    far = scale_message(40.0 * nominal, nominal)
    assert far.startswith("the current's RMS is 40 x the nominal record's") and "mA" not in far
    assert scale_message(nominal / 50.0, nominal).startswith("the current's RMS is 0.02 x")
    assert scale_message(nominal, None) is None and scale_message(nominal[:-1], nominal) is None


def test_every_reason_a_check_can_give_has_its_line():
    """A refused record says why in words: every reason the checks emit has a line (its own, with measured values,
    or reason_text's), so a new check cannot be added without one."""
    import re

    from phm_torch.online.input_contract import PIPELINE_CHECKS
    from phm_torch.online.reason_text import REASON_TEXT, SELF_EXPLAINED, reason_lines

    src = "".join(p.read_text() for p in (Path(__file__).resolve().parents[1] / "phm_torch" / "online").glob("*.py"))
    emitted = set(re.findall(r'reasons\.append\("([a-z_]+)"\)', src)) | set(PIPELINE_CHECKS) | {"pipeline"}
    assert {"sign", "offset", "spikes", "bench", "command"} <= emitted  # the scan finds the checks
    assert emitted <= set(REASON_TEXT) | set(SELF_EXPLAINED)
    assert reason_lines(["command", "plateau"]) == [f"plateau: {REASON_TEXT['plateau']}"]


@pytest.mark.torchscript
def _pretrained_nominal(noise: float, seed: int):
    """The pretrained pipeline (scripted module, loaded, its input contract), its nominal record (n,) [A] and RMS,
    that record with ``noise`` x RMS of white noise, and its time axis."""
    torch.set_num_threads(1)
    module = torch.jit.load(str(PIPELINE))
    model = TorchScriptPipeline(module, {})
    nominal = module.nominal_record.double()
    rms = float(nominal.pow(2).mean().sqrt())
    g = torch.Generator().manual_seed(seed)
    clean = nominal + noise * rms * torch.randn(nominal.numel(), generator=g, dtype=torch.float64)
    t = torch.arange(nominal.numel(), dtype=torch.float64) / 20000.0
    return module, model, InputContract.of(model, {}, None), nominal, rms, clean, t, g


@pytest.mark.torchscript  # the shipped TorchScript file
def test_a_probe_offset_is_read_at_rest_and_removed_from_a_near_nominal_record():
    """Near nominal the rest window sits on the nominal record within its noise; a probe's offset of 3 % of the RMS
    current there (under the ``offset`` check's 5 %) is measured and removed: the answer is the clean record's."""
    from phm_torch.online.rest_offset_check import CORRECT_SIGMAS, probe_offset, rest_window

    nominal = torch.zeros(1000, dtype=torch.float64)
    nominal[100:] = torch.sin((torch.arange(900, dtype=torch.float64) + 1.0) / 30.0)
    rms = float(nominal.pow(2).mean().sqrt())
    rest = rest_window(nominal)
    sigma = 0.01 * rms
    assert rest == 100 and probe_offset(nominal + 0.5 * CORRECT_SIGMAS * sigma / rest**0.5, nominal, sigma) is None
    assert probe_offset(nominal + 0.03 * rms, nominal, sigma) == pytest.approx(0.03 * rms)
    # a clean record's rest mean is 2.8 std off once in 200 records: noise, not a probe's offset, and left alone
    assert probe_offset(nominal + 2.8 * sigma / rest**0.5, nominal, sigma) is None
    assert probe_offset(nominal + 0.03 * rms, None, sigma) is None

    module, model, contract, _, rms, clean, t, g = _pretrained_nominal(0.01, 4)
    right = diagnose(model, Record(t, None, None, clean), contract)
    shifted = diagnose(model, Record(t, None, None, clean + 0.03 * rms), contract)
    assert right["probe_offset"] is None and shifted["probe_offset"] == pytest.approx(0.03 * rms, rel=0.1)
    assert not shifted["out_of_distribution"] and any("a probe's offset" in m for m in shifted["messages"])
    for name in FAULT_NAMES:
        assert shifted["k_hat"][name] == pytest.approx(right["k_hat"][name], abs=2e-3), name
    # with a bench's healthy record (baseline) the rest window compared holds that record's noise too: here its rest
    # mean sits 1.5 std of one record's noise off, as one in seven baselines does; at 3 std of the record's own noise
    # alone, about 7 % of the bench's clean records had their noise removed as a probe's offset
    base = module.nominal_record.double() + 0.01 * rms * torch.randn(clean.numel(), generator=g, dtype=torch.float64)
    rest = rest_window(module.nominal_record.double())
    base[:rest] += 1.5 * 0.01 * rms / rest**0.5 - (base[:rest] - module.nominal_record.double()[:rest]).mean()
    fired = 0
    for _ in range(150):
        noise = 0.01 * rms * torch.randn(clean.numel(), generator=g, dtype=torch.float64)
        record = Record(t, None, None, module.nominal_record.double() + noise)
        fired += diagnose(model, record, contract, bench_nominal=base)["probe_offset"] is not None
    assert fired <= 2


@pytest.mark.torchscript  # the shipped TorchScript file
def test_a_removed_probe_offset_widens_the_near_nominal_reading_by_its_own_error():
    """phm-track's reading of a record whose probe offset was removed: the offset was read over a 48-sample rest
    window, so its noise moves the near-nominal reading; the interval grows by that response (in quadrature) and holds
    the reading of the same record without an offset. A record without one keeps the calibrated half-widths."""
    from phm_torch.tracking.inspection import inspect_record
    from phm_torch.tracking.near_nominal import NearNominalFDI

    _, model, contract, _, rms, clean, t, _ = _pretrained_nominal(0.02, 11)
    near = NearNominalFDI.load(PIPELINE.with_suffix(".near_nominal.pt"))
    plain = inspect_record(model, Record(t, None, None, clean), contract, near_nominal=near)
    shifted = inspect_record(model, Record(t, None, None, clean + 0.03 * rms), contract, near_nominal=near)
    assert plain["probe_offset"] is None and shifted["probe_offset"] is not None

    def bounds(found):
        return torch.tensor([found["k_near_nominal_interval"][n] for n in FAULT_NAMES], dtype=torch.float64)

    def reading(found):
        return torch.tensor([found["k_near_nominal"][n] for n in FAULT_NAMES], dtype=torch.float64)

    w = near.half_widths(torch.tensor([plain["noise"]], dtype=torch.float64))[0]
    torch.testing.assert_close(bounds(plain)[:, 1], (reading(plain) + w).clamp(0.0, 1.0))
    damage = torch.tensor([n != "eccentricity_phase" for n in FAULT_NAMES])  # the phase's bound is clamped at 1
    w = near.half_widths(torch.tensor([shifted["noise"]], dtype=torch.float64))[0][damage]
    widened = (bounds(shifted)[:, 1] - reading(shifted))[damage]
    assert bool((widened >= w - 1e-9).all()) and float((widened / w).max()) > 1.5
    inside = (bounds(shifted)[:, 0] <= reading(plain)) & (reading(plain) <= bounds(shifted)[:, 1])
    assert bool(inside.all()), (reading(plain), bounds(shifted))


def test_a_position_range_of_a_units_factor_names_the_unit():
    """A position logged in degrees (57.3 x the command's range) or mrad (1000 x) gets a unit hint, like mA."""
    from phm_torch.online.command_check import CommandCheck, unit_hint

    assert "position [deg]" in unit_hint("position", 57.0) and "position [mrad]" in unit_hint("position", 1003.0)
    assert "'[mm]'" in unit_hint("position", 1003.0) and "'[mm]'" not in unit_hint("position", 57.0)
    assert unit_hint("position", 1.0) == "" and unit_hint("position", 8.0) == ""
    # the command check names the unit too: a record whose command column was logged in degrees
    assert "command [deg]" in CommandCheck(18.97, 0.0, 57.30, False).reason()
    assert "written in" not in CommandCheck(0.31, 0.002, 1.02, False).reason()


@pytest.mark.torchscript
def test_a_tracked_inspections_near_nominal_interval_holds_its_readings_within_the_timing_tolerance():
    """phm-track timing_tolerance=null: the near-nominal reading of a record 0.5 ms early is widened to its readings
    within the tolerance, which hold the on-time record's reading; at 0 it is read at its own timing."""
    from phm_torch.online.corruptions import delayed
    from phm_torch.tracking.inspection import inspect_record
    from phm_torch.tracking.near_nominal import NearNominalFDI

    _, model, contract, _, _, clean, t, _ = _pretrained_nominal(0.01, 11)
    near = NearNominalFDI.load(PIPELINE.with_suffix(".near_nominal.pt"))
    on_time = inspect_record(model, Record(t, None, None, clean), contract, near_nominal=near)
    late = Record(t, None, None, delayed(clean, -10))  # early: its rest window stays at rest (no offset read)
    exact = inspect_record(model, late, contract, near_nominal=near)
    tolerant = inspect_record(model, late, contract, near_nominal=near, timing_tolerance_s=1e-3)
    assert exact["timing_tolerance"] is None and tolerant["timing_tolerance"]["readings"] >= 21

    def bounds(found):
        return torch.tensor([found["k_near_nominal_interval"][n] for n in FAULT_NAMES], dtype=torch.float64)

    truth = torch.tensor([on_time["k_near_nominal"][n] for n in FAULT_NAMES], dtype=torch.float64)
    inside = lambda b: bool(((b[:, 0] <= truth + 1e-9) & (truth <= b[:, 1] + 1e-9)).all())
    assert not inside(bounds(exact)) and inside(bounds(tolerant))
    assert tolerant["k_near_nominal"] == exact["k_near_nominal"]  # the reading itself: the record as it came


@pytest.mark.torchscript
def test_a_tracked_inspection_is_read_again_moved_back_by_its_timing_scan_shift():
    """phm-track timing_align: near nominal the scan finds a record's timing to a sample or two; read moved back by
    it, a record 0.5 ms early gives the on-time record's estimate (read as it came, a gain drift well off)."""
    from phm_torch.online.corruptions import delayed
    from phm_torch.online.diagnosis import contract_for
    from phm_torch.online.export import read_metadata
    from phm_torch.tracking.inspection import inspect_record
    from phm_torch.tracking.timing_spread import ALIGN_TOLERANCE_S

    _, model, _, _, _, clean, t, _ = _pretrained_nominal(0.01, 11)
    contract = contract_for(model, read_metadata(PIPELINE), None)  # with the shipped timing threshold: the scan runs
    gain = lambda d: d["k_hat"]["gain_drift"]
    on_time = inspect_record(model, Record(t, None, None, clean), contract)
    early = Record(t, None, None, delayed(clean, -10))
    as_came = inspect_record(model, early, contract)
    aligned = inspect_record(model, early, contract, align_timing=True)
    assert as_came.get("timing_aligned_s") is None
    assert aligned["timing_aligned_s"] == pytest.approx(-5e-4, abs=2.5e-4)  # within the scan's 4 samples
    assert abs(gain(aligned) - gain(on_time)) < 0.5 * abs(gain(as_came) - gain(on_time))
    assert aligned["timing_tolerance"]["tolerance_s"] == ALIGN_TOLERANCE_S  # read within the scan's own error
