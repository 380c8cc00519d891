"""Deployment formats of the online pipeline (issue 27): the traceable OnlineStep equals the eager pipeline, every
format equals eager within 1e-5 (float32) on full and selected-sample records, with missing samples, batch 1 and
256, and out-of-distribution records; files load without phm_torch; phm-predict gives the same JSON from each."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest
import torch

from phm_torch.io import write_measurement
from phm_torch.online import OnlinePipeline
from phm_torch.online.formats import check_formats, format_path, in_dtype, write_checked, write_formats
from phm_torch.online.input_contract import PIPELINE_CHECKS, pipeline_reasons
from phm_torch.online.loaded import load_pipeline
from phm_torch.online.output_diffs import max_difference
from phm_torch.online.step import STEP_OUTPUTS, OnlineStep
from phm_torch.params import load_actuator
from phm_torch.prognostics import DamageModel
from phm_torch.surrogates.classifiers.polynomial_svm import PolynomialSVM
from phm_torch.surrogates.fdi_mlp import FDIMLP
from phm_torch.surrogates.full_signal_check import FullSignalCheck
from phm_torch.surrogates.gappy_pod import GappyPOD

N_FULL, N_MODES, N_POINTS = 2001, 6, 24
TOL = 1e-5
pytestmark = pytest.mark.torchscript  # scripts, saves or loads TorchScript on purpose


def _damage() -> DamageModel:
    f = torch.diag(torch.tensor([5e-4] * 6 + [0.0, 3e-4], dtype=torch.float64))
    f[1, 0] = 2e-4
    return DamageModel(f.tolist(), [1e-6] * 6 + [0.0, 1e-6], 100.0, 20000.0, 50.0, list(load_actuator().nominal_faults))


@pytest.fixture(scope="module")
def pipeline() -> OnlinePipeline:
    return small_pipeline()


def small_pipeline() -> OnlinePipeline:
    """A small float32 pipeline with every calibrated part a paper-scale one has but the forward surrogate."""
    torch.set_num_threads(1)
    torch.manual_seed(0)
    t = torch.linspace(0, 1, N_FULL, dtype=torch.float64)
    modes = torch.linalg.qr(torch.stack([torch.sin((i + 1) * 3.0 * t + i) for i in range(N_MODES)], 1))[0].float()
    mean = (1.0 + 0.5 * torch.sin(9 * t)).float()
    k = torch.rand(400, 8, generator=torch.Generator().manual_seed(0), dtype=torch.float64) ** 3
    k[:, 6:] = 0.5
    clf = PolynomialSVM(degree=2).fit(k.float(), k[:, :6].amax(1) < 0.3)
    widths = torch.full((2, 4, 8), 0.05) * torch.tensor([1.0, 2.0]).view(2, 1, 1)
    pipe = OnlinePipeline(
        GappyPOD(modes, mean, torch.linspace(0, N_FULL - 1, N_POINTS).round().long()),
        FDIMLP(N_MODES, 10),
        clf,
        _damage(),
        torch.tensor([0.02, 0.0, -0.02]),
        torch.tensor([1.0] * 6 + [0.0, 1.0]),
        N_FULL,
        residual_threshold=0.05,
        full_check=FullSignalCheck(modes, mean, residual_threshold=0.2, plateau_threshold=0.5),
        verdict=(-2.0, 0.3),
        k_half_widths=widths,
        interval_noise=torch.tensor([0.0, 0.05]),
        calibration_noise=0.01,
        residual_limits=([0.05, 0.2], [0.01, 0.1]),
        nominal_record=mean,
    )
    pipe.modes, pipe.mean_signal = modes, mean
    return pipe.eval()


def records(pipe: OnlinePipeline, n: int, seed: int = 1) -> torch.Tensor:
    """n in-span full records (n, N_FULL) [A] with 1 % white noise; the 2nd misses 3 samples, the 3rd is noise
    (out of distribution)."""
    g = torch.Generator().manual_seed(seed)
    x = pipe.mean_signal + (5.0 * torch.randn(n, N_MODES, generator=g)) @ pipe.modes.T
    x = x + 0.01 * torch.randn(x.shape, generator=g)
    if n > 2:
        x[1, pipe.gappy.indices[[2, 9, 17]]] = float("nan")
        x[2] = torch.randn(N_FULL, generator=g)
    return x


def eager(pipe: OnlinePipeline, x: torch.Tensor) -> dict[str, torch.Tensor]:
    """The outputs of the eager pipeline and its methods, named as OnlineStep's."""
    with torch.no_grad():
        k_hat, score, rul, ood, residual = pipe(x)
        full = x.shape[1] == N_FULL
        noise = pipe.noise_level(x) if full else torch.full((x.shape[0],), float("nan"), dtype=k_hat.dtype)
        lower, upper = pipe.k_interval(k_hat, noise) if full else pipe.k_interval(k_hat)
        found = pipeline_reasons(pipe, x)
    reasons = torch.tensor([[name in row for name in PIPELINE_CHECKS] for row in found])
    return {
        "k_hat": k_hat,
        "k_lower": lower,
        "k_upper": upper,
        "score": score,
        "rul": rul,
        "ood": ood,
        "residual": residual,
        "noise": noise,
        "p_faulty": pipe.faulty_probability(score),
        "reasons": reasons,
    }


def assert_equal_outputs(got: dict[str, torch.Tensor], ref: dict[str, torch.Tensor]) -> None:
    for name, value in ref.items():
        assert got[name].dtype == value.dtype, name
        torch.testing.assert_close(got[name], value, rtol=TOL, atol=TOL, equal_nan=True, msg=name)


@pytest.fixture(scope="module")
def files(pipeline, tmp_path_factory):
    out = tmp_path_factory.mktemp("formats") / "online.pt"
    return write_formats(pipeline, out, ["torchscript", "export"], {"provenance": None, "tracking_nrmse": [0.01, 0.2]})


@pytest.fixture(scope="module")
def loaded(files):
    return {fmt: load_pipeline(path) for fmt, path in files.items()}


def test_step_equals_the_eager_pipeline_and_its_reasons(pipeline):
    x = records(pipeline, 6)
    for full in (True, False):
        inputs = x if full else x.index_select(1, pipeline.gappy.indices)
        step = OnlineStep(pipeline, full)
        with torch.no_grad():
            got = dict(zip(STEP_OUTPUTS, step(inputs, torch.zeros(inputs.shape[1]))))
        ref = eager(pipeline, inputs)
        assert_equal_outputs(got, ref)
        assert bool(ref["ood"][2]) and not bool(ref["ood"][[0, 1, 3]].any())  # noise flagged, the gappy one not
        assert bool(torch.isnan(got["rul"][2]).all()) and bool(torch.isfinite(got["rul"][[0, 1, 3]]).all())
    assert torch.isfinite(ref["p_faulty"]).all() and torch.isfinite(ref["k_lower"]).all()


def test_step_with_a_bench_offset_equals_the_pipeline_on_the_rebased_records(pipeline):
    """The step subtracts the offset from the samples it reads only: the same as the pipeline on rebased records,
    with the noise as measured (before the offset)."""
    x = records(pipeline, 6)
    g = torch.Generator().manual_seed(5)
    bench = (
        pipeline.nominal_record
        + 0.05 * torch.sin(torch.linspace(0, 40, N_FULL))
        + 0.003 * torch.randn(N_FULL, generator=g)
    )
    offset = bench - pipeline.nominal_record
    with torch.no_grad():
        got = dict(zip(STEP_OUTPUTS, OnlineStep(pipeline, True)(x, offset)))
        ref = eager(pipeline, pipeline.rebase(x, bench))
        ref["noise"] = pipeline.noise_level(x)
        ref["k_lower"], ref["k_upper"] = pipeline.k_interval(ref["k_hat"], ref["noise"])
    assert_equal_outputs(got, ref)
    assert float((ref["noise"] - pipeline.noise_level(pipeline.rebase(x, bench))).abs().max()) > 1e-4  # it matters


@pytest.mark.parametrize("batch", [1, 256])
@pytest.mark.parametrize("full", [True, False])
def test_every_format_equals_eager(pipeline, loaded, batch, full):
    assert check_every_format(pipeline, loaded, batch, full) == len(loaded) * (1 if batch > 1 else 3)


@pytest.fixture(scope="module")
def loaded_float64(pipeline, tmp_path_factory):
    """The pipeline computing in float64 (phm-export dtype=float64) and its TorchScript and export files."""
    wide = in_dtype(pipeline, "float64")
    files = write_formats(wide, tmp_path_factory.mktemp("float64") / "online.pt", ["torchscript", "export"])
    return wide, {fmt: load_pipeline(path) for fmt, path in files.items()}


@pytest.mark.parametrize("batch", [1, 256])
@pytest.mark.parametrize("full", [True, False])
def test_every_float64_format_equals_eager_float64(loaded_float64, batch, full):
    wide, loaded = loaded_float64
    assert all(model.dtype == torch.float64 for model in loaded.values())
    assert check_every_format(wide, loaded, batch, full) == len(loaded) * (1 if batch > 1 else 3)


def check_every_format(pipeline: OnlinePipeline, loaded: dict, batch: int, full: bool) -> int:
    """Every loaded file equals eager on ``batch`` records (batch 1: a clean one, one missing 3 samples, noise);
    returns how many (file, batch) pairs were compared."""
    x = records(pipeline, max(batch, 3), seed=batch).to(pipeline.times.dtype)
    x = x if full else x.index_select(1, pipeline.gappy.indices)
    cases = [x[:batch]] if batch > 1 else [x[i : i + 1] for i in range(3)]  # batch 1: clean, 3 missing, noise
    compared = 0
    for fmt, model in loaded.items():
        assert model.format == fmt
        for xb in cases:
            r = model.run(xb)
            got = {
                name: getattr(r, name)
                for name in ("k_hat", "k_lower", "k_upper", "score", "p_faulty", "rul", "ood", "residual", "noise")
            }
            ref = eager(pipeline, xb)
            got["reasons"] = torch.tensor([[n in row for n in PIPELINE_CHECKS] for row in model.pipeline_reasons(xb)])
            if not bool(ref["ood"].any()):  # pipeline_reasons lists nothing for a record in distribution
                ref["reasons"] = got["reasons"] = torch.zeros(0)
            assert_equal_outputs(got, ref)
            compared += 1
    return compared


def test_export_file_loads_and_runs_without_phm_torch(pipeline, files, tmp_path):
    x = records(pipeline, 5)
    samples = x.index_select(1, pipeline.gappy.indices)
    torch.save({"x": x, "s": samples}, tmp_path / "x.pt")
    code = textwrap.dedent(f"""
        import sys, torch
        from torch.export.pt2_archive._package import load_pt2
        x = torch.load({str(tmp_path / "x.pt")!r}, weights_only=True)
        programs = load_pt2({str(files["export"])!r}).exported_programs   # torch.export.load gives 'model'
        full, samples = programs['model'].module(), programs['samples'].module()
        out = [full(x['x'], torch.zeros(x['x'].shape[1])), samples(x['s'], torch.zeros(x['s'].shape[1]))]
        torch.save([list(o) for o in out], {str(tmp_path / "out.pt")!r})
        assert not any(name.startswith('phm_torch') for name in sys.modules), 'phm_torch was imported'
    """)
    subprocess.run([sys.executable, "-c", code], check=True, cwd=tmp_path)
    loaded = torch.load(tmp_path / "out.pt", weights_only=True)
    for got, inputs in zip(loaded, (x, samples)):
        ref = eager(pipeline, inputs)
        out = dict(zip(STEP_OUTPUTS, got))
        for name in ("k_hat", "score", "rul", "ood", "residual", "k_lower", "p_faulty"):
            torch.testing.assert_close(out[name], ref[name], rtol=TOL, atol=TOL, equal_nan=True)


def test_predict_gives_the_same_json_from_every_format(pipeline, files, compose, tmp_path):
    from phm_torch.apps.predict import predict

    x = records(pipeline, 4, seed=3)
    zeros = torch.zeros(N_FULL, dtype=torch.float64)
    time = torch.arange(N_FULL, dtype=torch.float64) / 20000.0
    csvs = [
        str(
            write_measurement(
                tmp_path / f"r{i}.csv",
                {"time": time, "command": zeros, "position": zeros, "current": x[i].nan_to_num(1.0).double()},
            )
        )
        for i in range(4)
    ]
    lines = Path(csvs[1]).read_text().splitlines()  # record 1: its 3 missing samples as empty cells
    column = lines[0].split(",").index("current")
    for i in torch.isnan(x[1]).nonzero().flatten().tolist():
        cells = lines[i + 1].split(",")
        cells[column] = ""
        lines[i + 1] = ",".join(cells)
    Path(csvs[1]).write_text("\n".join(lines) + "\n")
    outs = {}
    for fmt, path in files.items():
        args = [f"pipeline={path}", f"measurements=[{','.join(csvs)}]", f"format={fmt}", f"baseline={csvs[0]}"]
        _, objects = predict(compose("predict", args))
        outs[fmt] = json.dumps(objects["records"], sort_keys=True)
    assert outs["torchscript"] == outs["export"]
    records_ = json.loads(outs["export"])
    assert records_[2]["out_of_distribution"] and records_[2]["rul_hours"] is None
    assert records_[1]["k_interval"] is not None and not records_[1]["out_of_distribution"]


def test_bad_formats_and_files_are_one_line_errors(files, loaded, tmp_path):
    with pytest.raises(ValueError, match="format: unknown format 'tflite'"):
        check_formats(["torchscript", "tflite"])
    with pytest.raises(ValueError, match="format: unknown format 'tflite'"):
        load_pipeline(files["export"], "tflite")
    with pytest.raises(ValueError, match="is a 'export' file, not format='torchscript'"):
        load_pipeline(files["export"], "torchscript")
    wrong = tmp_path / "online.pt2"
    wrong.write_bytes(files["torchscript"].read_bytes())  # TorchScript named as an export file
    with pytest.raises(ValueError, match="holds a 'torchscript' pipeline but its name ends as a 'export'"):
        load_pipeline(wrong)
    with pytest.raises(ValueError, match=r"records: expected \(B, 2001\) full records or \(B, 24\)"):
        loaded["export"].run(torch.zeros(2, 100))
    assert format_path(tmp_path / "a.pt", "aoti").name == "a.aoti.pt2"
    assert format_path(tmp_path / "a.aoti.pt2", "torchscript").name == "a.pt"


def test_write_checked_reloads_every_format_as_predict_reads_it(pipeline, tmp_path):
    """phm-evaluate's and phm-export's write + reload check: the files beside out, each within 1e-5 of eager; a
    NaN on one side only (here: a file whose RUL is no longer NaN for the OOD record) is an infinite difference."""
    x = records(pipeline, 4)
    checked = write_checked(pipeline, tmp_path / "online.pt", ["export", "torchscript"], {"provenance": None}, x)
    assert list(checked["files"]) == ["export", "torchscript"]
    assert Path(checked["files"]["export"]).name == "online.pt2" and Path(checked["files"]["torchscript"]).is_file()
    assert all(0.0 <= d < TOL for d in checked["max_abs_diff"].values()), checked
    rul = torch.tensor([[1.0, 2.0, 3.0], [float("nan")] * 3])
    assert max_difference(rul, rul.clone()) == 0.0 and max_difference(rul.nan_to_num(0.0), rul) == float("inf")


def test_evaluate_refuses_an_unknown_export_format_before_any_work(compose, tmp_path):
    from phm_torch.apps.evaluate import evaluate_rul

    with pytest.raises(ValueError, match="format: unknown format 'tflite'"):
        evaluate_rul(
            compose(
                "evaluate",
                ["export_formats=[torchscript,tflite]", f"data_dir={tmp_path / 'none'}", f"out_dir={tmp_path / 'out'}"],
            )
        )
    assert not (tmp_path / "out").exists()


def test_export_cli_refuses_an_unknown_format(run_cli):
    result = run_cli("phm_torch.apps.export", "format=[torchscript,tflite]")
    assert result.returncode == 2
    assert "format: unknown format 'tflite'" in result.stderr


@pytest.fixture(scope="module")
def aoti_file(pipeline, tmp_path_factory):
    """AOTInductor: both programs compiled into one package (about 2-3 min of C++ compilation on 2 cores)."""
    return write_formats(pipeline, tmp_path_factory.mktemp("aoti") / "online.pt", ["aoti"])["aoti"]


@pytest.mark.slow
def test_aoti_package_equals_eager_and_runs_without_phm_torch(pipeline, aoti_file, tmp_path):
    path = aoti_file
    assert path.name == "online.aoti.pt2"
    model = load_pipeline(path)
    assert model.format == "aoti"
    x = records(pipeline, 256, seed=5)
    for inputs in (x, x.index_select(1, pipeline.gappy.indices)):
        for xb in (inputs, inputs[:1], inputs[1:2], inputs[2:3]):  # batch 256; clean, 3 missing, noise
            r = model.run(xb)
            ref = eager(pipeline, xb)
            ref.pop("reasons")
            assert_equal_outputs({name: getattr(r, name) for name in ref}, ref)
    # the package's FDI alone, as the pipeline's method: its products autotuned (formats.FDI_INDUCTOR_OPTIONS) are
    # inductor's own kernels, another float32 summation order over the 1000 samples (the pretrained pipeline: up to
    # 1.0e-5 on 512 records, median 5e-8), hence three times the steps' tolerance
    samples = x.index_select(1, pipeline.gappy.indices)
    complete = samples[torch.isfinite(samples).all(1)]
    with torch.no_grad():
        for xb in (complete[:1], complete):
            got, ref = model.k_hat_of_samples(xb), pipeline.k_hat_of_samples(xb)
            torch.testing.assert_close(got, ref, rtol=3 * TOL, atol=3 * TOL)
    with pytest.raises(ValueError, match="complete samples only"):
        model.k_hat_of_samples(samples[:2])  # the 2nd misses 3 samples
    torch.save(x, tmp_path / "x.pt")
    code = textwrap.dedent(f"""
        import sys, torch
        from torch._inductor.package import load_package
        x = torch.load({str(tmp_path / "x.pt")!r}, weights_only=True)
        out = load_package({str(path)!r}, model_name='model')(x, torch.zeros(x.shape[1]))
        torch.save(list(out), {str(tmp_path / "out.pt")!r})
        assert not any(name.startswith('phm_torch') for name in sys.modules), 'phm_torch was imported'
    """)
    subprocess.run([sys.executable, "-c", code], check=True, cwd=tmp_path)
    out = dict(zip(STEP_OUTPUTS, torch.load(tmp_path / "out.pt", weights_only=True)))
    ref = eager(pipeline, x)
    for name in ("k_hat", "score", "rul", "ood", "residual"):
        torch.testing.assert_close(out[name], ref[name], rtol=TOL, atol=TOL, equal_nan=True)


@pytest.mark.slow
def test_cpp_example_runs_the_aoti_package_as_python_does(pipeline, aoti_file, tmp_path):
    """examples/aoti_cpp: built with g++ against the torch wheel's libtorch (about 40 s), it runs one record through
    the package with AOTIModelPackageLoader and prints what Python's load_package gives (and eager, within 1e-5)."""
    if shutil.which("g++") is None:
        pytest.skip("no g++ on this machine: the C++ example cannot be built")
    root = Path(__file__).resolve().parents[1] / "examples" / "aoti_cpp"
    binary = tmp_path / "phm_aoti"
    subprocess.run(["bash", str(root / "build.sh"), str(binary)], check=True, capture_output=True, timeout=600)
    model = load_pipeline(aoti_file)
    x = records(pipeline, 3, seed=11)  # clean, 3 missing samples, noise (OOD)
    cases = [(x[i : i + 1], "model") for i in range(3)] + [(x[1:2].index_select(1, pipeline.gappy.indices), "samples")]
    for xb, name in cases:
        xb.numpy().astype("<f4").tofile(tmp_path / "record.f32")
        run = subprocess.run(
            [str(binary), str(aoti_file), str(tmp_path / "record.f32"), name],
            capture_output=True,
            text=True,
            check=True,
            timeout=120,
        )
        lines = run.stdout.strip().splitlines()
        assert len(lines) == len(STEP_OUTPUTS)
        python = model._outputs(xb, None)
        ref = eager(pipeline, xb)
        for i, (line, out_name) in enumerate(zip(lines, STEP_OUTPUTS)):
            index, *values = line.split()
            assert int(index) == i
            got = torch.tensor([float(v) for v in values], dtype=torch.float64)
            want = python[out_name].double().flatten()
            torch.testing.assert_close(got, want, rtol=0.0, atol=0.0, equal_nan=True, msg=out_name)  # same kernels
            if out_name in ref and out_name != "reasons":
                torch.testing.assert_close(got, ref[out_name].double().flatten(), rtol=TOL, atol=TOL, equal_nan=True)
        assert (lines[STEP_OUTPUTS.index("rul")].split()[1] == "nan") == bool(ref["ood"][0])
    bad = subprocess.run([str(binary), str(aoti_file)], check=False, capture_output=True, text=True)
    assert bad.returncode == 2 and "usage:" in bad.stderr


@pytest.mark.slow
def test_the_pretrained_pipeline_as_an_aoti_package_equals_its_torchscript_file(tmp_path):
    """The AOTInductor lowering on the pipeline it was made for (MLP classifiers, whose tanh it rewrites; the small
    pipeline above has polynomial ones): every output phm-predict reads within 1e-5 of the shipped TorchScript file
    (relative above 1: the RUL in hours), the package's FDI program within 3e-5 (about 1.5 min of compilation)."""
    from phm_torch.online.from_torchscript import pipeline_from_torchscript, probe_records, rewrite_pipeline
    from phm_torch.online.output_diffs import output_diffs

    shipped = Path(__file__).resolve().parents[1] / "pretrained" / "online_surrogates_best.pt"
    done = rewrite_pipeline(shipped, tmp_path / "online.pt", ["aoti"])
    package, file = load_pipeline(done["files"]["aoti"]), load_pipeline(shipped)
    pipeline, _ = pipeline_from_torchscript(shipped)
    probe = probe_records(pipeline, seed=4)
    with torch.no_grad():
        diffs = output_diffs(package, file, probe)
        assert max(d["scaled"] for d in diffs.values()) <= TOL, diffs
        samples = probe.index_select(1, pipeline.gappy.indices)
        complete = samples[torch.isfinite(samples).all(1)]
        got, ref = package.k_hat_of_samples(complete), file.module.k_hat_of_samples(complete)
        torch.testing.assert_close(got, ref, rtol=3 * TOL, atol=3 * TOL)
    # the lowering found the crossing's scores: each classifier's three tanh layers kept exact there, the marker gone
    from phm_torch.online.aoti_lowering import _in_classifier, for_inductor, tanh_for_inductor
    from phm_torch.online.formats import export_programs

    lowered = for_inductor(export_programs(pipeline)["model"].module())
    calls = [n for n in lowered.graph.nodes if n.op == "call_function"]
    exact = [n for n in calls if n.target is torch.ops.aten.tanh.default and _in_classifier(n)]
    assert len(exact) == 6 and any(n.target is tanh_for_inductor for n in calls)
    assert not any("crossing_marker" in str(n.target) for n in lowered.graph.nodes)
