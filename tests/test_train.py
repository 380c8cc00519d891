"""``phm-train`` end to end on a small synthetic store: metrics.json, the bundle, sweeps, bad input."""

from __future__ import annotations

import json
import math
from pathlib import Path
from types import SimpleNamespace

import h5py
import pytest
import torch
from surrogate_data import faults, health, signals, write_store

from phm_torch.apps.train import settings_from_config, train_surrogates
from phm_torch.pipelines.train import classifier_set, monitor_rows
from phm_torch.surrogates import POD, GappyPOD, SurrogateBundle
from phm_torch.surrogates.data import load_store
from phm_torch.surrogates.full_signal_check import FullSignalCheck
from phm_torch.surrogates.ood_calibration import ood_thresholds

pytestmark = pytest.mark.torchscript  # scripts, saves or loads TorchScript on purpose

REQUIRED = (
    "err_alpha_median",
    "err_alpha_iqr",
    "err_k",
    "fdi_mae",
    "classifier_accuracy",
    "missed_fault_rate",
    "false_alarm_rate",
    "fdi_latency_us_p50",
)
QUICK = (
    "n_modes=10",
    "n_points=16",
    "n_hidden=12",
    "eval.latency_repeats=50",
    "trainer.enable_progress_bar=false",
    "classifier_refine.rounds=0",
)  # the synthetic store records no assessment to label with


@pytest.fixture(scope="module")
def store(tmp_path_factory) -> Path:
    return write_store(tmp_path_factory.mktemp("store"), {"train": 400, "val": 100}, noise=0.01)


@pytest.fixture(scope="module")
def lm_run(store, compose, tmp_path_factory):
    out = tmp_path_factory.mktemp("lm")
    cfg = compose("train", [f"data_dir={store}", f"out_dir={out}", *QUICK, "model.fit.max_epochs=25"])
    return train_surrogates(cfg)


def test_metrics_json(lm_run):
    _metrics, objects = lm_run
    written = json.loads((objects["out_dir"] / "metrics.json").read_text())
    for key in REQUIRED:
        assert key in written, key
    assert len(written["fdi_mae"]) == 8
    for key in (
        "err_alpha_median",
        "err_alpha_iqr",
        "err_k",
        "classifier_accuracy",
        "missed_fault_rate",
        "false_alarm_rate",
    ):
        assert 0.0 <= written[key] <= 1.0, key  # fractions
    # The synthetic family is rank 10 and learnable: the pipeline must actually work.
    assert written["err_alpha_median"] < 0.05
    assert written["err_k"] < 0.05
    assert written["classifier_accuracy"] > 0.85
    assert written["fdi_latency_us_p50"] > 0
    assert written["err_k_noise"] >= 0 and written["err_k_missing"] >= 0
    assert set(written["err_k_by_fault_count"]) == {"0", "1", "2", "3+"}
    # per-signal aggregates of the paper's formula: the mean of the roots is at most the pooled root (Jensen)
    assert written["err_k_median_per_signal"] > 0
    assert 0 < written["err_k_mean_per_signal"] <= written["err_k"] + 1e-12
    lo, hi = written["err_k_ci95"]
    assert lo <= written["err_k"] <= hi and hi - lo > 0
    assert (objects["out_dir"] / "logs").is_dir()  # CSV logger
    assert list((objects["out_dir"] / "checkpoints").glob("*.ckpt"))
    # the epoch is chosen on 5 % of the training signals held out from the fit, not on val
    assert (written["n_fdi_fit"], written["n_fdi_monitor"], written["n_val"]) == (380, 20, 100)
    assert len(objects["trainer"].val_dataloaders.dataset) == 20


def test_monitor_rows_are_a_disjoint_seeded_split():
    fit, monitor = monitor_rows(1000, 0.05, seed=3)
    assert len(monitor) == 50 and len(fit) == 950
    assert torch.equal(torch.cat([fit, monitor]).sort().values, torch.arange(1000))
    assert torch.equal(monitor_rows(1000, 0.05, seed=3)[1], monitor)
    assert not torch.equal(monitor_rows(1000, 0.05, seed=4)[1], monitor)
    everything, none = monitor_rows(10, 0.0, seed=0)
    assert none is None and torch.equal(everything, torch.arange(10))
    with pytest.raises(ValueError, match="leaves 1 of 2 training signals"):
        monitor_rows(2, 0.4, seed=0)


def test_bundle_round_trip(lm_run, store):
    _metrics, objects = lm_run
    path = objects["out_dir"] / "surrogates.pt"
    bundle = SurrogateBundle.load(path, expect={"n_modes": 10, "n_points": 16, "n_hidden": 12})
    arrays = torch.load(objects["out_dir"] / "predictions.pt", weights_only=True)
    from surrogate_data import faults, signals

    k = faults(100, 17)  # the val split of write_store (seed 0 + 17)
    samples = bundle.compress(signals(k, 0.01, 1))
    assert torch.allclose(bundle.fdi(samples), arrays["k_hat"], atol=1e-5)
    assert torch.allclose(bundle(samples), arrays["k_hat"], atol=1e-5)
    # estimate: the online FDI on full records (noise level estimated per record), float64
    estimate = bundle.estimate(signals(k, 0.01, 1))
    assert estimate.dtype == torch.float64 and torch.allclose(estimate, arrays["k_hat"].double(), atol=1e-5)
    scripted = torch.jit.script(bundle)  # exportable as it is (issue 5)
    holed = samples.clone()
    holed[:, :2] = float("nan")
    assert torch.allclose(scripted(holed), bundle.fdi(holed), atol=1e-6)
    out = bundle.diagnose(samples)
    assert set(out) == {"k_hat", "alpha", "residual", "out_of_distribution"}
    assert float(out["out_of_distribution"].float().mean()) < 0.1
    score = bundle.health_score(k)
    assert torch.allclose(score, arrays["score"])
    assert torch.equal(bundle.is_healthy(k), score > 0)
    assert bundle.sample_times.shape == (16,) and float(bundle.sample_times.max()) <= 800 / 20000.0
    meta = torch.load(path, weights_only=True)["meta"]
    assert meta["health_convention"].startswith("health_score > 0: healthy")
    # A far out-of-distribution record is flagged.
    odd = samples.clone()
    odd[:, ::2] += 50.0
    assert bool(bundle.diagnose(odd)["out_of_distribution"].all())
    # the full-record threshold is the training quantile, saved and restored with the bundle
    written = json.loads((objects["out_dir"] / "metrics.json").read_text())
    assert float(bundle.full_residual_threshold) == pytest.approx(written["ood_full_residual_threshold"])
    assert 0.0 < written["ood_full_residual_threshold"] < 1.0
    assert float(bundle.plateau_threshold) == pytest.approx(written["ood_plateau_threshold"])
    assert bundle.full_signal_check().plateau_threshold == pytest.approx(written["ood_plateau_threshold"])
    assert bundle.full_signal_check().roughness_threshold == pytest.approx(written["ood_roughness_threshold"])
    assert 1.0 <= written["ood_roughness_threshold"] <= 1.3
    # the verdict on estimates comes from the verdict classifier, fitted on the training records' estimates
    assert bundle.verdict_classifier is not None and bundle.verdict_classifier.name == bundle.classifier.name
    torch.testing.assert_close(bundle.verdict_score(arrays["k_hat"]), arrays["score_chain"].to(torch.float64))
    right = (arrays["score_chain"] > 0) == arrays["healthy"]
    assert written["chain_accuracy"] == pytest.approx(float(right.double().mean()))
    assert 0.5 < written["chain_accuracy_health_classifier"] <= 1.0


def test_bundle_from_another_configuration(lm_run, tmp_path):
    path = lm_run[1]["out_dir"] / "surrogates.pt"
    with pytest.raises(ValueError, match="bundle from another configuration: n_modes=10 in the file, 22 expected"):
        SurrogateBundle.load(path, expect={"n_modes": 22})
    junk = tmp_path / "junk.pt"
    torch.save({"format": "something else"}, junk)
    with pytest.raises(ValueError, match="not a surrogate bundle"):
        SurrogateBundle.load(junk)
    with pytest.raises(ValueError, match="does not exist"):
        SurrogateBundle.load(tmp_path / "missing.pt")
    # a bundle written before the n_layers option has one hidden layer
    blob = torch.load(path, weights_only=True)
    del blob["meta"]["n_layers"], blob["meta"]["n_members"], blob["meta"]["verdict_classifier"]
    blob["tensors"] = {k: v for k, v in blob["tensors"].items() if not k.startswith("verdict_classifier.")}
    old = tmp_path / "old.pt"
    torch.save(blob, old)
    before = SurrogateBundle.load(old, expect={"n_layers": 1, "n_members": 1})
    assert before.network.n_layers == 1 and before.verdict_classifier is None  # and no verdict classifier
    with pytest.raises(ValueError, match="n_layers=1 in the file, 2 expected"):
        SurrogateBundle.load(old, expect={"n_layers": 2})


def test_end_to_end_adam_and_resume_mismatch(store, compose, tmp_path):
    over = [
        f"data_dir={store}",
        f"out_dir={tmp_path / 'e2e'}",
        *QUICK,
        "model=fdi_e2e",
        "model.fit.max_epochs=80",
        "selector=greedy",
        "loggers=[csv]",
        "n_layers=2",
        "n_members=2",
    ]
    metrics, objects = train_surrogates(compose("train", over))
    assert metrics["model"] == "adam_e2e" and math.isfinite(metrics["err_k"]) and metrics["err_k"] < 0.1
    assert (metrics["n_layers"], metrics["n_members"]) == (2, 2)
    bundle = SurrogateBundle.load(objects["out_dir"] / "surrogates.pt", expect={"n_layers": 2, "n_members": 2})
    assert bundle.network.w_in.shape[0] == 2
    x = bundle.compress(torch.stack([bundle.pod.mean_] * 3) + 0.01)
    assert torch.equal(torch.jit.script(bundle)(x), bundle.fdi(x))
    last = objects["out_dir"] / "checkpoints" / "last.ckpt"
    assert last.is_file()
    with pytest.raises(ValueError, match="checkpoint from another configuration: n_hidden=12 in the checkpoint vs 9"):
        train_surrogates(compose("train", [*over, "n_hidden=9", f"ckpt_path={last}"]))


@pytest.mark.parametrize(
    "change,match",
    [
        ({"drop": {"val": "current"}}, r"split 'val' lacks an array"),
        ({"n_time": 700}, r"current has shape \(60, 801\), expected \(60, 700\)"),
    ],
)
def test_bad_store(change, match, compose, tmp_path):
    store = write_store(tmp_path / "bad", {"train": 60, "val": 20}, **change)
    with pytest.raises(ValueError, match=match):
        train_surrogates(compose("train", [f"data_dir={store}", f"out_dir={tmp_path / 'o'}", *QUICK]))


def test_a_non_finite_record_past_the_first_read_block_is_named(tmp_path):
    store = write_store(tmp_path / "inf", {"train": 600, "val": 20})
    with h5py.File(store / "dataset.h5", "r+") as f:
        f["train/current"][530, 7] = float("inf")  # READ_ROWS = 512: the second block
    with pytest.raises(ValueError, match=r"split 'train': current row 530 holds NaN or inf"):
        load_store(store, {"train": "train", "val": "val"})


def test_ood_thresholds_are_block_size_free_and_grow_with_the_noise():
    y = signals(faults(300, 5), noise=0.02)  # residuals well above round-off
    pod = POD(10).fit(y)
    gappy = GappyPOD(pod.modes_, pod.mean_, torch.arange(0, y.shape[1], 40))
    check = FullSignalCheck(pod.modes_, pod.mean_)
    clean = ood_thresholds(y, gappy, check, 0.0, 0.99, seed=1, block_rows=300)
    # float32 round-off of energy - explained differs with the batch shape (~1e-4 of the residual)
    assert ood_thresholds(y, gappy, check, 0.0, 0.99, seed=1, block_rows=7) == pytest.approx(clean, rel=1e-3)
    with torch.no_grad():  # the whole-array computation it replaces
        direct = (
            float(torch.quantile(gappy(gappy.select(y))[1].double(), 0.99)),
            float(torch.quantile(check.residual(y).double(), 0.99)),
        )
    assert clean == pytest.approx(direct, rel=1e-3)
    noisy = ood_thresholds(y, gappy, check, 0.05, 0.99, seed=1, block_rows=64)
    assert noisy == ood_thresholds(y, gappy, check, 0.05, 0.99, seed=1, block_rows=64)  # seeded
    assert noisy[0] > 2 * clean[0] and noisy[1] > 2 * clean[1]
    with pytest.raises(ValueError, match="eval.ood_quantile"):
        ood_thresholds(y, gappy, check, 0.0, 1.5, seed=1)


def test_missing_split_and_config_errors(compose, tmp_path):
    store = write_store(tmp_path / "nosplit", {"train": 60})
    with pytest.raises(ValueError, match="split 'val' is not in the store"):
        train_surrogates(compose("train", [f"data_dir={store}", f"out_dir={tmp_path / 'o'}", *QUICK]))
    with pytest.raises(ValueError, match="n_points=5 < n_modes=10"):
        train_surrogates(compose("train", [f"data_dir={store}", "n_points=5", "n_modes=10"]))
    with pytest.raises(ValueError, match="holds no finished dataset store"):
        train_surrogates(compose("train", [f"data_dir={tmp_path / 'nothing'}", *QUICK]))
    for override, message in (  # one bad setting each: the error names it
        ("loggers=[wandb]", "loggers must be a list"),
        ("threads=0", "threads"),
        ("monitor_fraction=0.5", "monitor_fraction must be < 0.5"),
        ("monitor_fraction=-0.1", "monitor_fraction must be >= 0, got -0.1"),
        ("n_layers=0", "n_layers must be >= 1, got 0"),
        ("n_members=2", "n_members=2 needs model=fdi_adam or model=fdi_e2e"),
        ("+model.network.n_layers=2", "model.network.n_layers: set the top-level n_layers instead"),
        (
            "calibration.verdict_max_missed_fault_rate=1.0",
            r"verdict_max_missed_fault_rate must be in \[0, 1\), got 1.0",
        ),
        ("calibration.verdict_max_missed_fault_rate=-0.1", "verdict_max_missed_fault_rate must be >= 0, got -0.1"),
        ("model.fit.shifted_copies=-1", "model.fit.shifted_copies must be >= 0, got -1"),
        ("model.fit.max_shift=0", "model.fit.shifted_copies=4 needs model.fit.max_shift >= 1"),
    ):
        with pytest.raises(ValueError, match=message):
            train_surrogates(compose("train", [f"data_dir={store}", *QUICK, override]))
    for overrides, message in (  # the held-out calibration needs held-out rows and a verdict classifier
        (["monitor_fraction=0"], "set monitor_fraction > 0"),
        (["verdict_classifier=false"], "set verdict_classifier=true"),
    ):
        with pytest.raises(ValueError, match=message):
            settings_from_config(
                compose("train", [f"data_dir={store}", "calibration.verdict_max_missed_fault_rate=0.05", *overrides])
            )


def test_verdict_calibrated_on_the_fdis_monitor_rows(store, compose, tmp_path):
    """calibration.verdict_max_missed_fault_rate: the verdict is calibrated on the training rows held out from the
    FDI's fit (the monitor rows, 5 % of 400 here), and metrics.json says what that calibration saw and set."""
    cfg = compose(
        "train",
        [
            f"data_dir={store}",
            f"out_dir={tmp_path}",
            *QUICK,
            "model.fit.max_epochs=10",
            "monitor_fraction=0.25",
            "calibration.verdict_max_missed_fault_rate=0.05",
        ],
    )
    metrics, objects = train_surrogates(cfg)
    report = json.loads((tmp_path / "metrics.json").read_text())["verdict_calibration"]
    assert report == metrics["verdict_calibration"]
    _, monitor = monitor_rows(400, 0.25, 0)
    assert report["n_held_out"] == len(monitor) == 100 and report["n_faulty"] > 10
    before, after = report["held_out_missed_fault_rate"]
    assert after <= 0.05 + 1.0 / report["n_faulty"] and after <= before
    assert report["threshold"] == pytest.approx(float(objects["bundle"].verdict_classifier.threshold))


def test_shifted_copies_read_each_record_moved_and_reduced_as_the_inputs_are():
    from types import SimpleNamespace

    from phm_torch.pipelines.train.fdi import shifted_copies
    from phm_torch.surrogates import POD, GappyPOD

    records = torch.linspace(0.0, 1.0, 200, dtype=torch.float32).pow(2).repeat(6, 1) * torch.arange(1.0, 7.0)[:, None]
    pod = POD(3).fit(records + 0.01 * torch.randn(records.shape, generator=torch.Generator().manual_seed(0)))
    gappy = GappyPOD(pod.modes_, pod.mean_, torch.arange(10, 190, 20))
    k = torch.rand(6, 8, generator=torch.Generator().manual_seed(1))
    alpha = gappy(gappy.select(records))[0]
    fit = SimpleNamespace(shifted_copies=2, max_shift=3, inputs="gappy")
    x, y = shifted_copies([alpha, k], records, SimpleNamespace(gappy=gappy, pod=pod), fit, seed=0)
    assert x.shape == (18, 3) and torch.equal(y, k.repeat(3, 1)) and torch.equal(x[:6], alpha)  # the records first
    assert not torch.allclose(x[6:12], alpha)  # then each read moved (a rising record reads another level)
    moved = [gappy(records[:, gappy.indices + s])[0] for s in range(-3, 4)]  # every shift within the bound
    assert all(any(torch.allclose(row, m[i], atol=1e-5) for m in moved) for i, row in enumerate(x[6:12]))
    full = shifted_copies(
        [pod(records), k],
        records,
        SimpleNamespace(gappy=gappy, pod=pod),
        SimpleNamespace(shifted_copies=1, max_shift=3, inputs="full"),
        seed=0,
    )[0]
    assert full.shape == (12, 3)


def test_shifted_copies_are_for_precomputed_inputs_only():
    from phm_torch.pipelines.train import FDIModel

    fit = {"max_epochs": 5, "patience": 2, "batch_size": 8, "inputs": "gappy", "shifted_copies": 2, "max_shift": 3}
    assert FDIModel(fit, None, end_to_end=False).fit.shifted_copies == 2
    with pytest.raises(ValueError, match="model.fit.shifted_copies is for a network fitted on precomputed inputs"):
        FDIModel(fit, None, end_to_end=True)
    with pytest.raises(ValueError, match=r"model.fit: unknown setting\(s\) \['shift'\]"):
        FDIModel({**fit, "shift": 1}, None, end_to_end=False)


def test_threads_setting(compose):
    from phm_torch.apps import common

    before = torch.get_num_threads()
    try:
        common.set_threads(compose("train", ["threads=1"]))
        assert torch.get_num_threads() == 1
        common.set_threads(compose("train"))  # null: left alone
        assert torch.get_num_threads() == 1
        assert compose("evaluate").threads is None
    finally:
        torch.set_num_threads(before)


def test_cli_reports_a_missing_store(run_cli, tmp_path):
    proc = run_cli("phm_torch.apps.train", f"data_dir={tmp_path / 'none'}", timeout=120)
    assert proc.returncode == 2
    assert "phm-train: error: data_dir" in proc.stderr and "run phm-generate first" in proc.stderr


@pytest.mark.parametrize(
    "name,key,values",
    [
        ("ablation_modes", "n_modes", "5,10,15,22,30"),
        ("ablation_hidden", "n_hidden", "5,10,20,50,100"),
        ("ablation_points", "n_points", "22,30,45,60"),
        ("ablation_selector", "selector", "som,qdeim,greedy,min_error,uniform,random"),
    ],
)
def test_sweep_configs(name, key, values):
    from hydra import compose, initialize_config_dir
    from hydra.core.global_hydra import GlobalHydra

    from phm_torch.params import CONF_DIR

    GlobalHydra.instance().clear()
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        cfg = compose("train", [f"experiment={name}"], return_hydra_config=True)
    assert str(cfg.hydra.sweeper.params[key]).replace(" ", "") == values


def test_best_experiment_composes(compose):
    cfg = compose("train", ["experiment=surrogates_best"])
    assert cfg.selector._target_.endswith("UniformSelector") and cfg.model.optimizer == "adam"
    assert (cfg.n_modes, cfg.n_points, cfg.n_hidden, cfg.n_layers, cfg.n_members) == (40, 1000, 256, 2, 4)
    assert cfg.model.fit.patience >= cfg.model.fit.max_epochs  # the whole cosine schedule
    assert cfg.model.network.input_scaling == "robust"  # the model group's own setting is kept
    robust = compose("train", ["experiment=robust_30_points"])
    assert robust.gappy.estimator == "bayesian" and robust.model.end_to_end and robust.model.optimizer == "adam"
    assert (robust.n_modes, robust.n_points, robust.selector._target_.rsplit(".", 1)[-1]) == (22, 30, "SOMSelector")


def test_multirun_jobs_write_into_their_own_directories(store, run_cli, tmp_path):
    sweep = tmp_path / "sweep"
    proc = run_cli(
        "phm_torch.apps.train",
        "-m",
        f"data_dir={store}",
        *QUICK,
        "model.fit.max_epochs=2",
        "n_hidden=4,6",
        f"hydra.sweep.dir={sweep}",
        timeout=240,
    )
    assert proc.returncode == 0, proc.stderr[-2000:]
    hidden = [json.loads((sweep / job / "metrics.json").read_text())["n_hidden"] for job in ("0", "1")]
    assert hidden == [4, 6]
    assert (sweep / "1" / "surrogates.pt").is_file()


def test_classifier_also_learns_from_the_labels_split(compose, tmp_path):
    """The assessment-only labels split joins the classifier's training set (and only when asked)."""
    data_dir = write_store(tmp_path / "s", {"train": 40, "val": 10, "labels": 300})
    train = SimpleNamespace(k=faults(40, 0).float(), healthy=health(faults(40, 0)))
    k, h = classifier_set(settings_from_config(compose("train", [f"data_dir={data_dir}"])), train.k, train.healthy)
    assert k.shape == (340, 8) and h.shape == (340,) and k.dtype == torch.float64
    assert torch.equal(h[:40], train.healthy)
    assert torch.equal(h[40:], health(faults(300, 34)))  # write_store's seed for the 3rd split
    k_only, _ = classifier_set(
        settings_from_config(compose("train", [f"data_dir={data_dir}", "classifier_labels=false"])),
        train.k,
        train.healthy,
    )
    assert k_only.shape == (40, 8)
    plain = write_store(tmp_path / "p", {"train": 40, "val": 10})  # a store without labels: train only
    settings = settings_from_config(compose("train", [f"data_dir={plain}"]))
    assert classifier_set(settings, train.k, train.healthy)[0].shape == (40, 8)


def test_bayesian_gappy_estimator_round_trips_through_the_bundle(store, compose, tmp_path):
    over = [
        f"data_dir={store}",
        f"out_dir={tmp_path / 'bayes'}",
        *QUICK,
        "model.fit.max_epochs=10",
        "n_modes=6",
        "n_points=5",
        "gappy.estimator=bayesian",  # fewer points than modes: the prior decides
        "verdict_classifier=false",
    ]  # the health classifier judges the estimates
    metrics, objects = train_surrogates(compose("train", over))
    assert metrics["gappy_estimator"] == "bayesian" and math.isfinite(metrics["err_alpha_median"])
    assert metrics["chain_accuracy"] == metrics["chain_accuracy_health_classifier"]
    path = objects["out_dir"] / "surrogates.pt"
    bundle = SurrogateBundle.load(path)
    assert bundle.gappy.bayesian and bundle.verdict_classifier is None
    torch.testing.assert_close(bundle.gappy.noise_covariance, objects["bundle"].gappy.noise_covariance)
    arrays = torch.load(objects["out_dir"] / "predictions.pt", weights_only=True)
    from surrogate_data import faults, signals

    samples = bundle.compress(signals(faults(100, 17), 0.01, 1))
    assert torch.allclose(bundle.fdi(samples), arrays["k_hat"], atol=1e-5)
    holed = samples.clone()
    holed[:, 1] = float("nan")
    assert torch.allclose(torch.jit.script(bundle)(holed), bundle.fdi(holed), atol=1e-6)
    # the online pipeline accepts it with fewer present samples than modes (no n_m + 1 floor)
    from phm_torch.online import OnlinePipeline
    from phm_torch.prognostics import DamageModel

    rate = torch.diag(torch.tensor([1e-4] * 6 + [0.0, 1e-4]))
    damage = DamageModel(rate.tolist(), [1e-6] * 6 + [0.0, 1e-6], 100.0, 20000.0, 50.0, [0.0] * 6 + [0.5, 0.5])
    online = OnlinePipeline.from_bundle(bundle, damage, torch.zeros(3), torch.ones(8) / 8)
    k_hat, _, _, ood, _ = online(samples.float())
    torch.testing.assert_close(k_hat, bundle.fdi(samples.float()))
    assert online.min_count == 4 and float(ood.float().mean()) < 0.5
    with pytest.raises(ValueError, match="gappy.estimator must be one of"):
        train_surrogates(compose("train", [*over, "gappy.estimator=kalman"]))


def test_noise_aware_end_to_end_run_and_its_pipeline(store, compose, tmp_path):
    from test_online import damage

    from phm_torch.online import OnlinePipeline
    from phm_torch.online.pipeline import NOISE_WINDOW
    from phm_torch.surrogates import noise_level

    base = [f"data_dir={store}", *QUICK, "model.fit.max_epochs=30"]
    with pytest.raises(ValueError, match="noise_input=true needs noisy training records: model.end_to_end=true"):
        train_surrogates(compose("train", [*base, f"out_dir={tmp_path / 'a'}", "+model.network.noise_input=true"]))
    with pytest.raises(ValueError, match="model.network.max_noise: it is model.augment.noise"):
        train_surrogates(
            compose("train", [*base, f"out_dir={tmp_path / 'b'}", "model=fdi_e2e", "+model.network.max_noise=0.2"])
        )
    metrics, objects = train_surrogates(
        compose(
            "train",
            [
                *base,
                f"out_dir={tmp_path / 'c'}",
                "model=fdi_e2e",
                "+model.network.noise_input=true",
                "model.augment.noise=0.05",
            ],
        )
    )
    assert math.isfinite(metrics["err_k"]) and math.isfinite(metrics["err_k_noise"])
    bundle = SurrogateBundle.load(objects["out_dir"] / "surrogates.pt")
    net = bundle.network
    assert (net.noise_input, net.default_noise, net.max_noise) == (True, 0.01, 0.05)  # eval.noise, augment.noise
    assert bundle.metadata()["noise_input"] is True
    torch.testing.assert_close(net.in_center, objects["bundle"].network.in_center)
    # the pipeline tells the network each full record's estimated noise; selected samples alone: the default
    pipe = OnlinePipeline.from_bundle(bundle, damage(), torch.zeros(3), torch.ones(8)).eval()
    clean = signals(faults(4, 5)).to(torch.float64)
    noise = torch.randn(clean.shape, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    noisy = clean + 0.04 * clean.pow(2).mean(1, keepdim=True).sqrt() * noise
    with torch.no_grad():
        level = pipe.noise_level(noisy)
        assert bool(((level - 0.04).abs() < 0.006).all())
        k_full = pipe(noisy)[0]
        k_told = bundle.fdi(bundle.compress(noisy).float(), noise=noise_level(noisy, NOISE_WINDOW).float())
        k_samples = pipe(bundle.compress(noisy))[0]
        k_sent = torch.jit.script(pipe)(bundle.compress(noisy), noise_level(noisy, NOISE_WINDOW))[0]  # level sent along
    torch.testing.assert_close(k_sent, k_full)
    with pytest.raises(ValueError, match=r"online: noise must be \(B,\)"):
        pipe(noisy, torch.zeros(2))
    torch.testing.assert_close(k_full.float(), k_told, atol=1e-5, rtol=0)
    torch.testing.assert_close(k_samples.float(), bundle.fdi(bundle.compress(noisy).float()), atol=1e-5, rtol=0)
    assert float((k_full - k_samples).abs().max()) > 1e-4
