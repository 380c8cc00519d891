"""An eager OnlinePipeline rebuilt from a TorchScript pipeline file (phm_torch/online/from_torchscript.py): the
shipped pretrained file (written by an older phm_torch, its bundle gone) and a freshly exported one give the same
outputs as the file, every part the current class has is set; ``phm-export pipeline=`` rewrites a file in other
formats; the shipped ``.pt2`` equals the shipped ``.pt`` and pretrained/README.md gives both files' SHA-256."""

from __future__ import annotations

import hashlib
import json
import re
from pathlib import Path

import pytest
import torch
from test_export_formats import N_FULL, N_MODES, _damage, records, small_pipeline
from torch import nn

from phm_torch.io import Measurement, read_measurement, write_measurement
from phm_torch.online import OnlinePipeline
from phm_torch.online.consistency import ConsistencyCheck
from phm_torch.online.export import export_torchscript, read_metadata
from phm_torch.online.from_torchscript import convert_scripted, load_scripted, pipeline_from_torchscript
from phm_torch.online.loaded import as_loaded, load_pipeline
from phm_torch.online.output_diffs import OUTPUTS, output_diffs
from phm_torch.params import CONF_DIR
from phm_torch.surrogates.classifiers.mlp import MLPClassifier
from phm_torch.surrogates.classifiers.rbf_svm import RBFSVM
from phm_torch.surrogates.fdi_ensemble import FDIEnsemble
from phm_torch.surrogates.forward import ForwardSurrogate

pytestmark = pytest.mark.torchscript  # loads TorchScript on purpose

PRETRAINED = CONF_DIR.parent / "pretrained"
PT, PT2 = PRETRAINED / "online_surrogates_best.pt", PRETRAINED / "online_surrogates_best.pt2"
# the pretrained pipeline as an older phm_torch wrote it (the shipped files are its conversion, pretrained/README.md):
# the conversion of a file that lacks the newer parts
OLD = Path(__file__).parent / "data" / "pretrained_v0.pt"
EXACT = 1e-6  # float32 pipeline: the same arithmetic gives the same numbers (measured: 0)
# Records with missing samples: the gappy layer's Woodbury path now starts from its solve matrix (centred @ G^-1 V^T)
# where the pretrained file multiplies by V and G^-1 in turn; the same least squares, rounded otherwise in float32:
# alpha moves by 3e-7 of its size, k_hat by up to 9.4e-6, the verdict score (slope ~15 per unit of k) by 2.4e-5 of
# its value, the RUL by 2e-5 of its value (measured on 32 noisy nominal records missing 3 random samples each)
MISSING_ATOL, MISSING_RTOL = 2e-5, 1e-4
TEST_EXTRAS = {"modes", "mean_signal"}  # set on the test pipelines by small_pipeline, not by the class


def _run(model, x: torch.Tensor) -> dict[str, torch.Tensor | None]:
    r = as_loaded(model).run(x)
    return {name: getattr(r, name) for name in OUTPUTS}


def assert_same_outputs(
    a, b, x: torch.Tensor, atol: float = EXACT, rtol: float = EXACT, file_noise: bool = False
) -> None:
    """Every output phm-predict reads of pipelines a and b on records x within atol + rtol |b| (NaN where b's).

    ``file_noise``: b is the pretrained file, whose noise estimate is the whole record's (the code's is windowed
    now): a's intervals are read at b's estimate, and the estimates agree within 10 % where the noise is 1 %."""
    got, ref = _run(a, x), _run(b, x)
    if file_noise and ref["k_lower"] is not None and bool(torch.isfinite(ref["noise"]).all()):
        got["k_lower"], got["k_upper"] = a.k_interval(got["k_hat"], ref["noise"])
        noisy = ref["noise"] > 0.005
        torch.testing.assert_close(got["noise"][noisy], ref["noise"][noisy], rtol=0.1, atol=0.0)
        got["noise"] = ref["noise"]
    for name in OUTPUTS:
        assert (got[name] is None) == (ref[name] is None), name
        if ref[name] is not None:
            assert got[name].dtype == ref[name].dtype, name
            torch.testing.assert_close(got[name], ref[name], atol=atol, rtol=rtol, equal_nan=True, msg=name)


def _layout(module: nn.Module) -> dict[str, set[str]]:
    """What a module instance holds: its plain attributes (with ``training``), buffers, parameters, submodules."""
    return {
        "attributes": {k for k in vars(module) if not k.startswith("_")} - TEST_EXTRAS,
        "buffers": {k for k, _ in module.named_buffers(recurse=False)},
        "parameters": {k for k, _ in module.named_parameters(recurse=False)},
        "children": {k for k, _ in module.named_children()},
    }


def assert_complete(converted: nn.Module, fresh: dict[type, nn.Module]) -> None:
    """Every module of ``converted`` holds every attribute, buffer, parameter and submodule that a constructed
    instance of its class (``fresh``) holds, with values of the same type."""
    checked = 0
    for name, module in converted.named_modules():
        ref = fresh.get(type(module))
        if ref is None:
            continue
        have, want = _layout(module), _layout(ref)
        for kind in want:
            assert want[kind] <= have[kind], (name or "pipeline", type(module).__name__, kind, want[kind] - have[kind])
        for attr in want["attributes"]:
            a, b = getattr(module, attr), getattr(ref, attr)
            if a is not None and b is not None:
                assert type(a) is type(b), (name, attr, type(a), type(b))
        checked += 1
    assert checked >= len({type(m) for m in converted.modules()} & set(fresh)), checked


def rich_pipeline() -> OnlinePipeline:
    """small_pipeline with the other parts: a noise-aware FDI ensemble, a verdict classifier of its own (MLP) and an
    RBF health classifier, a consistency check (forward surrogate), a health stop and an unidentified component."""
    base = small_pipeline()
    torch.manual_seed(1)
    k = torch.rand(300, 8, generator=torch.Generator().manual_seed(2), dtype=torch.float64) ** 3
    k[:, 6:] = 0.5
    clf = RBFSVM(n_landmarks=40).fit(k.float(), k[:, :6].amax(1) < 0.3)
    verdict = MLPClassifier(hidden=(6, 5))
    verdict.flat_weights.normal_(0.0, 0.5)
    verdict.k_mean.fill_(0.1)
    forward = ForwardSurrogate(N_MODES, n_hidden=7)
    check = ConsistencyCheck(
        forward,
        base.mean_signal,
        base.modes,
        base.gappy.indices,
        torch.tensor([[5.0, 9.0], [6.0, 10.0]]),
        torch.tensor([0.0, 0.05]),
    )
    pipe = OnlinePipeline(
        base.gappy,
        FDIEnsemble(N_MODES, 9, n_members=3, noise_input=True),
        clf,
        _damage(),
        base.deltas,
        base.direction,
        N_FULL,
        residual_threshold=0.05,
        full_check=base.full_check,
        verdict=(-2.0, 0.3),
        k_half_widths=base.k_half_widths,
        interval_noise=base.interval_noise,
        calibration_noise=0.01,
        residual_limits=([0.05, 0.2], [0.01, 0.1]),
        nominal_record=base.nominal_record,
        verdict_classifier=verdict,
        consistency=check,
        fdi_health_stop=[0],
        unidentified=[1],
        coarse=20,
        min_present=0.5,
    )
    pipe.modes, pipe.mean_signal = base.modes, base.mean_signal
    return pipe.eval()


@pytest.fixture(scope="module")
def pretrained():
    torch.set_num_threads(1)
    module = load_scripted(OLD)
    pipeline, derived = convert_scripted(module, OLD)
    return module, pipeline, derived


def _nominal_records(pipeline: OnlinePipeline, n: int = 4, seed: int = 0) -> torch.Tensor:
    """The pipeline's nominal record and n copies with 1 % white noise, (n + 1, n_full) [A]."""
    base = pipeline.nominal_record
    g = torch.Generator().manual_seed(seed)
    noisy = base + 0.01 * base.pow(2).mean().sqrt() * torch.randn(n, base.shape[0], generator=g)
    return torch.cat([base.unsqueeze(0), noisy])


def _foreign(pipeline: OnlinePipeline) -> torch.Tensor:
    """A record of noise alone (1, n_full) [A]: out of distribution."""
    g = torch.Generator().manual_seed(9)
    return pipeline.nominal_record.pow(2).mean().sqrt() * torch.randn(1, pipeline.n_full, generator=g)


def test_pretrained_file_converts_with_the_absent_parts_as_the_constructor_sets_them(pretrained):
    module, pipe, derived = pretrained
    assert isinstance(pipe, OnlinePipeline) and not pipe.training
    # the file predates these: derived by the constructor, as for a pipeline built without them
    assert {
        "coarse_index",
        "health_stop_index",
        "unknown_shift",
        "residual_limit.values",
        "residual_limit.levels",
    } <= set(derived)
    stored = module.state_dict()
    assert not set(derived) & set(stored)
    n_t = pipe.times.shape[0]
    assert pipe.coarse_index.tolist() == [*range(0, n_t, pipe.coarse), *([n_t - 1] if (n_t - 1) % pipe.coarse else [])]
    assert pipe.health_stop_index.numel() == 0 and not pipe.mixed_stop
    assert not bool(pipe.unknown_shift.any())
    assert pipe.residual_limit.values.tolist() == [pytest.approx(pipe.residual_threshold)]
    assert pipe.residual_limit.levels.tolist() == [0.0]
    assert not pipe.has_consistency and isinstance(pipe.consistency_check, nn.Identity)
    assert bool(torch.isnan(pipe.consistency(pipe.nominal_record.unsqueeze(0))).all())
    # every tensor of the file is the converted pipeline's, bit for bit, and so are its plain attributes
    mine = pipe.state_dict()
    for key, value in stored.items():
        assert torch.equal(mine[key], value), key
    for name in ("n_full", "n_points", "min_count", "residual_threshold", "coarse", "bisections", "noise_window"):
        assert getattr(pipe, name) == getattr(module, name), name
    assert type(pipe.fdi).__name__ == "FDIEnsemble" and pipe.noise_aware and pipe.fdi.noise_input
    assert pipe.verdict_classifier is not pipe.classifier  # the file's two classifiers differ
    converted, metadata = pipeline_from_torchscript(OLD)
    assert_same_outputs(converted, pipe, pipe.nominal_record.unsqueeze(0))
    assert metadata == read_metadata(OLD) and metadata["provenance"]["actuator"]["name"] == "ema_reference"


def test_pretrained_conversion_sets_every_part_the_current_classes_have(pretrained):
    rich, small = rich_pipeline(), small_pipeline()
    fresh = {type(m): m for pipe in (small, rich) for m in pipe.modules()}
    assert {OnlinePipeline, FDIEnsemble, MLPClassifier} <= set(fresh)
    assert_complete(pretrained[1], fresh)


def test_pretrained_conversion_equals_the_file_on_complete_and_foreign_records(pretrained):
    module, pipe, _ = pretrained
    x = torch.cat([_nominal_records(pipe), _foreign(pipe)])
    with torch.no_grad():
        for inputs in (x, x.index_select(1, pipe.gappy.indices)):  # full records, selected samples
            assert_same_outputs(pipe, module, inputs, file_noise=True)
            samples = inputs.shape[1] == pipe.n_points
            # the selected samples with their noise sent along, as a system sending only those would
            noise = module.noise_level(x)
            for a, b in zip(pipe(inputs, noise if samples else None), module(inputs, noise if samples else None)):
                torch.testing.assert_close(a, b, atol=EXACT, rtol=EXACT, equal_nan=True)
        ood, rul = pipe(x)[3], pipe(x)[2]
    assert not bool(ood[:-1].any()) and bool(ood[-1])
    assert bool(torch.isnan(rul[-1]).all()) and bool(torch.isfinite(rul[:-1]).all())


def test_pretrained_conversion_with_missing_samples_differs_only_by_the_gappy_rounding(pretrained):
    module, pipe, _ = pretrained
    x = _nominal_records(pipe, 6, seed=1)
    g = torch.Generator().manual_seed(2)
    for row in x:
        row[pipe.gappy.indices[torch.randperm(pipe.n_points, generator=g)[:3]]] = float("nan")
    x = torch.cat([x, _foreign(pipe)])
    with torch.no_grad():
        for inputs in (x, x.index_select(1, pipe.gappy.indices)):
            assert_same_outputs(pipe, module, inputs, atol=MISSING_ATOL, rtol=MISSING_RTOL, file_noise=True)
            got, ref = pipe(inputs), module(inputs)
            assert torch.equal(got[3], ref[3]) and not bool(got[3][:-1].any())
            assert bool(got[3][-1]) == (inputs.shape[1] == pipe.n_full)  # the full-record check flags the foreign one
            assert float((got[0] - ref[0]).abs().max()) > 0.0  # the rounding is there (else tighten the bound)
        # with the file's own gappy layer, the rest of the converted pipeline gives the file's numbers
        own, _ = convert_scripted(module, OLD)
        own.gappy = module.gappy
        for inputs in (x, x.index_select(1, pipe.gappy.indices)):
            assert_same_outputs(own, module, inputs, file_noise=True)


@pytest.mark.parametrize("make", [small_pipeline, rich_pipeline])
def test_a_freshly_exported_pipeline_round_trips(make, tmp_path):
    """script -> file -> convert gives back the pipeline: the same state, every attribute, the same outputs
    (consistency included) on clean, missing-sample and foreign records, full and selected samples."""
    pipe = make()
    path = tmp_path / "online.pt"
    export_torchscript(pipe, path, {"provenance": None, "tracking_nrmse": [0.01, 0.2]})
    back, metadata = pipeline_from_torchscript(path)
    assert metadata == {"provenance": None, "tracking_nrmse": [0.01, 0.2]}
    assert_complete(back, {type(m): m for m in pipe.modules()})
    assert set(back.state_dict()) == set(pipe.state_dict())
    for key, value in pipe.state_dict().items():
        torch.testing.assert_close(back.state_dict()[key], value, rtol=0, atol=0, equal_nan=True, msg=key)
    assert (back.verdict_classifier is back.classifier) == (pipe.verdict_classifier is pipe.classifier)
    assert (back.has_consistency, back.mixed_stop) == (pipe.has_consistency, pipe.mixed_stop)
    x = records(pipe, 6)
    with torch.no_grad():
        for inputs in (x, x.index_select(1, pipe.gappy.indices)):
            assert_same_outputs(back, pipe, inputs)
            torch.testing.assert_close(back.consistency(inputs), pipe.consistency(inputs), equal_nan=True)
        assert_same_outputs(back, load_pipeline(path), x)


def test_a_file_that_is_no_torchscript_pipeline_is_a_value_error(tmp_path):
    torch.save({"w": torch.zeros(2)}, tmp_path / "pickle.pt")
    torch.jit.save(torch.jit.script(nn.Linear(2, 2)), tmp_path / "linear.pt")
    (tmp_path / "text.pt").write_text("not a pipeline")
    cases = {
        tmp_path / "none.pt": "no such file",
        tmp_path / "text.pt": r"text.pt.*not a readable exported pipeline",
        tmp_path / "pickle.pt": r"pickle.pt' is no TorchScript archive",
        tmp_path / "linear.pt": r"linear.pt' holds a TorchScript Linear, not an online pipeline",
        PT2: r"online_surrogates_best.pt2' is an 'export' file",
    }
    for path, message in cases.items():
        with pytest.raises(ValueError, match=f"^pipeline: .*{message}"):
            pipeline_from_torchscript(path)


@pytest.mark.slow  # every format; ~40 s (test_export_formats writes each fast)
def test_export_app_rewrites_a_torchscript_file_in_other_formats(compose, tmp_path):
    from phm_torch.apps.export import export

    source = tmp_path / "online.pt"
    metadata = {"provenance": None, "tracking_nrmse": [0.01, 0.2], "damage": {"rate": [[0.1]]}}
    export_torchscript(small_pipeline(), source, metadata)
    metrics, _ = export(compose("export", [f"pipeline={source}", "format=[export]", f"out={tmp_path / 'new.pt'}"]))
    assert metrics["files"] == {"export": str(tmp_path / "new.pt2")} and metrics["derived"] == []
    assert max(metrics["max_abs_diff_input"].values()) == 0.0 and metrics["max_abs_diff_reloaded"] < 1e-5
    written = read_metadata(tmp_path / "new.pt2")
    assert {k: written[k] for k in metadata} == metadata and written["format"] == "export"
    x = records(small_pipeline(), 4)
    assert_same_outputs(load_pipeline(tmp_path / "new.pt2"), load_pipeline(source), x, atol=1e-5, rtol=1e-5)
    with pytest.raises(ValueError, match="out: the 'torchscript' file .* would replace the input pipeline"):
        export(compose("export", [f"pipeline={source}", "format=[torchscript]", f"out={source}"]))


def test_export_cli_refuses_a_missing_pipeline_file(run_cli):
    result = run_cli("phm_torch.apps.export", "pipeline=nowhere.pt", "format=[export]")
    assert result.returncode == 2 and "pipeline: no such file 'nowhere.pt'" in result.stderr


def test_shipped_pt2_equals_the_shipped_pt(pretrained):
    """The shipped export file is the converted pretrained pipeline: on complete records (the nominal one, noisy
    copies, a foreign one) it gives the TorchScript file's numbers, full records and selected samples."""
    pipe = pretrained[1]
    pt, pt2 = load_pipeline(PT), load_pipeline(PT2)
    assert (pt.format, pt2.format) == ("torchscript", "export")
    assert read_metadata(PT2)["provenance"] == read_metadata(PT)["provenance"]
    x = torch.cat([_nominal_records(pipe, 2), _foreign(pipe)])
    for inputs in (x, x.index_select(1, pipe.gappy.indices)):
        assert_same_outputs(pt2, pt, inputs)
    diffs = output_diffs(pt2, pt, x)
    assert max(d["abs"] for d in diffs.values()) <= EXACT, diffs


def test_shipped_files_match_the_sha256_in_the_pretrained_readme():
    text = (PRETRAINED / "README.md").read_text()
    for path in (PT, PT2):
        found = re.findall(rf"`{re.escape(path.name)}`[^\n]*?`([0-9a-f]{{64}})`", text)
        assert found, f"pretrained/README.md gives no SHA-256 for {path.name}"
        assert set(found) == {hashlib.sha256(path.read_bytes()).hexdigest()}, path.name


def test_predict_gives_the_same_json_from_the_shipped_pt_and_pt2(pretrained, compose, tmp_path):
    """The bundled example record and the pipeline's nominal record give identical JSON from both files; a record
    missing 3 samples the same verdict and numbers within the gappy rounding (see MISSING_RTOL)."""
    from phm_torch.apps.predict import predict

    example = CONF_DIR.parent / "examples" / "workbench_hidden_cogging.csv"
    ex = read_measurement(example)
    nominal = tmp_path / "nominal.csv"
    current = pretrained[1].nominal_record.double().numpy()
    write_measurement(nominal, Measurement(ex.time, ex.command, ex.position, current, sample_rate=20000.0))
    lines = nominal.read_text().splitlines()
    column = lines[0].split(",").index("current")
    for i in pretrained[1].gappy.indices[[3, 100, 998]].tolist():
        cells = lines[i + 1].split(",")
        cells[column] = ""
        lines[i + 1] = ",".join(cells)
    holed = tmp_path / "holed.csv"
    holed.write_text("\n".join(lines) + "\n")
    outs = {}
    for path in (PT, PT2):
        _, objects = predict(compose("predict", [f"pipeline={path}", f"measurements=[{example},{nominal},{holed}]"]))
        outs[path.suffix] = objects["records"]
    # the timing check reads the consistency statistic, which only the TorchScript file serves (a program's outputs
    # carry the checks' flags, not their statistics): the .pt2 lists it as skipped, everything else is the same
    for pt, pt2 in zip(outs[".pt"][:2], outs[".pt2"][:2]):
        assert pt["timing_check"]["ok"] and pt2["timing_check"] is None and pt2["checks_skipped"][-1] == "timing"
    same = [
        {**r, "timing_check": None, "checks_skipped": [c for c in r["checks_skipped"] if c != "timing"]}
        for r in outs[".pt"][:2] + outs[".pt2"][:2]
    ]
    assert json.dumps(same[:2], sort_keys=True) == json.dumps(same[2:], sort_keys=True)
    a, b = outs[".pt"][2], outs[".pt2"][2]
    assert a["healthy"] == b["healthy"] and not a["out_of_distribution"] and not b["out_of_distribution"]
    for name, value in a["k_hat"].items():
        assert b["k_hat"][name] == pytest.approx(value, abs=MISSING_ATOL), name
    for name, value in a["rul_hours"].items():
        assert b["rul_hours"][name] == (None if value is None else pytest.approx(value, rel=MISSING_RTOL)), name


def test_run_passes_the_measured_noise_to_the_forward_only_where_it_is_the_same_estimate():
    """TorchScriptPipeline.run measures each record's noise for the report; a pipeline whose forward estimates it the
    same way (the first samples) is given that level instead of estimating it again, with the same outputs; the
    original file (its noise_level read the whole record) and a rebased record estimate their own."""
    shipped, original = load_pipeline(PT), load_pipeline(OLD)
    assert shipped.noise_reusable and not original.noise_reusable
    base = shipped.module.nominal_record.unsqueeze(0)
    x = base + 0.02 * base.abs().mean() * torch.randn(6, base.shape[1], generator=torch.Generator().manual_seed(4))
    x[3, 40:43] = float("nan")  # a record with missing samples takes the same path
    with torch.no_grad():
        ref = shipped.module(x.to(shipped.dtype))
    got = shipped.run(x)
    for a, b in zip((got.k_hat, got.score, got.rul, got.ood, got.residual), ref):
        torch.testing.assert_close(a, b, rtol=0, atol=0, equal_nan=True)


def test_conversion_derives_the_fdi_fold_instead_of_copying_the_old_files_flag():
    """The original file predates the fold (it has no fdi_folded), the previous shipped one said False for its
    ensemble: the converted pipeline folds it, and its FDI alone equals the file's layer-by-layer answer."""
    from phm_torch.online.from_torchscript import pipeline_from_torchscript

    old = load_scripted(OLD)
    assert not bool(getattr(old, "fdi_folded", False))
    pipe, _ = pipeline_from_torchscript(OLD)
    assert pipe.fdi_folded and pipe.folded_fdi.two_stage
    base = old.nominal_record.unsqueeze(0)
    x = base + 0.02 * base.abs().mean() * torch.randn(8, base.shape[1], generator=torch.Generator().manual_seed(6))
    samples = x.index_select(1, old.gappy.indices).to(old.times.dtype)
    with torch.no_grad():
        layers = old.fdi(old.gappy(samples)[0], None)  # the noise-aware ensemble at its default level
        torch.testing.assert_close(pipe.k_hat_of_samples(samples), layers, rtol=0, atol=1e-5)


def test_conversion_does_not_copy_a_stale_fold_flag(tmp_path):
    """A file written when its FDI could not be folded says fdi_folded False; the converter derives it again."""
    from phm_torch.online.from_torchscript import pipeline_from_torchscript

    pipe = small_pipeline()
    assert pipe.fdi_folded
    pipe.fdi_folded = False  # as a file of an older phm_torch recorded it
    export_torchscript(pipe, tmp_path / "old.pt")
    assert not bool(load_scripted(tmp_path / "old.pt").fdi_folded)
    converted, _ = pipeline_from_torchscript(tmp_path / "old.pt")
    assert converted.fdi_folded


@pytest.mark.slow  # 40-100 s on 2 cores
def test_export_app_writes_a_float64_file_of_a_float32_one(compose, run_cli, tmp_path):
    """dtype=float64: the file computes in float64 (its metadata says so, phm-predict casts records to it) and
    equals the float32 file within the float32 floor; a bad dtype is one line naming it, exit status 2."""
    from phm_torch.apps.export import export

    source = tmp_path / "online.pt"
    export_torchscript(small_pipeline(), source, {"provenance": None})
    out = tmp_path / "wide.pt"
    metrics, _ = export(
        compose("export", [f"pipeline={source}", "format=[torchscript,export]", f"out={out}"] + ["dtype=float64"])
    )
    assert metrics["max_abs_diff_reloaded"] < 1e-9  # each file against the float64 eager pipeline it was made from
    for path in (tmp_path / "wide.pt", tmp_path / "wide.pt2"):
        assert read_metadata(path).get("pipeline", {"dtype": "float64"})["dtype"] == "float64"
        wide = load_pipeline(path)
        assert wide.dtype == torch.float64
        x = records(small_pipeline(), 4)
        got, ref = wide.run(x), load_pipeline(source).run(x)
        for name in ("k_hat", "score", "rul", "residual"):
            a, b = getattr(got, name), getattr(ref, name)
            assert a.dtype == torch.float64 and (b.dtype == torch.float32 or name != "k_hat")
            torch.testing.assert_close(a, b.double(), atol=1e-4, rtol=1e-4, equal_nan=True, msg=name)
    result = run_cli("phm_torch.apps.export", f"pipeline={source}", "format=[export]", "dtype=float16")
    assert result.returncode == 2 and "dtype: must be one of float32, float64 or null" in result.stderr
