"""phm-generate and the dataset store at tiny scale (LF signals, short command, few test frequencies):
identical manifests for the same config whatever the sharding and interruptions (SIGKILL included),
checksum-verified chunks, refusal to mix configs, lazy reads and the LightningDataModule; the
assessment-only labels split (its own seed stream and chunks, the same guarantees) and read_labelled."""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import h5py
import numpy as np
import pytest
import torch
import yaml
from omegaconf import OmegaConf

from phm_torch.apps import common
from phm_torch.apps.generate import generate
from phm_torch.data.datamodule import EMADataModule
from phm_torch.data.generation import STREAMS, DatasetSpec, seed_streams
from phm_torch.data.spec import SPLITS
from phm_torch.data.store import DatasetStore, read_labelled
from phm_torch.params import CONF_DIR
from phm_torch.simulator import EMASimulator

APP = "phm_torch.apps.generate"
TINY = (
    "dataset.fidelity=lf",
    "command.duration=0.02",
    "dataset.n_train=10",
    "dataset.n_val=3",
    "dataset.n_rul=2",
    "dataset.chunk_size=6",
    "assessment.sweep.frequencies=[15,30,60,90,130]",
    "assessment.sweep.cycles=3",
    "assessment.sweep.group_size=5",
    "assessment.sweep.max_extensions=0",  # the 4-cycle reading: these tests are about the store, not the labels
    "assessment.sweep.refine=0",
    "assessment.sweep.rotor_positions=1",  # one rest angle: a third of the shipped labels' cost
    "progress=false",
    "threads=1",
    "+dataset.healthy_fraction=null",  # the paper's scaling: no calibration pilot
    "dataset.n_labels=0",
)
N_CHUNKS = 3  # 1 + 10 + 3 + 2 = 16 rows in chunks of 6
# the same with 20 labels: at most 8 per chunk -> 3 chunks of 7 rows (the last padded with one k_0 row)
LABELLED = (*TINY[:-1], "dataset.n_labels=20", "+dataset.label_chunk_size=8")


def _manifest(path: Path) -> dict:
    return json.loads((path / "manifest.json").read_text())


@pytest.fixture(scope="module")
def reference(tmp_path_factory, compose):
    """One uninterrupted tiny run: (data_dir, metrics)."""
    data_dir = tmp_path_factory.mktemp("ref") / "store"
    metrics, _ = generate(compose("generate", [*TINY, f"data_dir={data_dir}"]))
    return data_dir, metrics


@pytest.fixture(scope="module")
def killed_and_resumed(tmp_path_factory, spawn_cli):
    """A CLI run SIGKILLed once its first chunk exists, a stale temp file left, then the same command
    again; also a bad-input CLI run. Returns (data_dir, resumed run, bad run)."""
    cwd = tmp_path_factory.mktemp("kill")
    data_dir = cwd / "store"
    args = (*TINY, f"data_dir={data_dir}")
    bad = spawn_cli(APP, ("dataset.n_train=0", f"data_dir={cwd / 'bad'}"), cwd)
    proc = spawn_cli(APP, args, cwd)
    first = data_dir / "chunks" / "chunk_00000.h5"
    deadline = time.monotonic() + 240
    while not first.exists() and proc.poll() is None and time.monotonic() < deadline:
        time.sleep(0.05)
    killed = proc.poll() is None
    proc.send_signal(signal.SIGKILL)
    proc.communicate()
    assert killed, "the run finished before it could be killed"
    (data_dir / "chunks" / ".chunk_00001.h5.0123456789ab.tmp").write_bytes(b"half-written")
    assert not (data_dir / "manifest.json").exists()
    resumed = spawn_cli(APP, args, cwd)
    out, err = resumed.communicate(timeout=300)
    bad_out, bad_err = bad.communicate(timeout=120)
    return (
        data_dir,
        subprocess.CompletedProcess(resumed.args, resumed.returncode, out, err),
        subprocess.CompletedProcess(bad.args, bad.returncode, bad_out, bad_err),
    )


def test_store_contents(reference):
    data_dir, metrics = reference
    assert metrics["complete"] and metrics["chunks"] == {
        "total": N_CHUNKS,
        "computed": N_CHUNKS,
        "reused": 0,
        "repaired": 0,
    }
    m = _manifest(data_dir)
    assert {s: v["count"] for s, v in m["splits"].items()} == {"nominal": 1, "train": 10, "val": 3, "rul": 2}
    assert m["splits"]["nominal"]["healthy"] == 1
    with DatasetStore(data_dir, verify=True) as store:
        tr = store.split("train")
        assert tr.K.shape == (10, 8) and tr.K.dtype == np.float64
        assert tr.current.shape == (10, 401) and tr.current.dtype == np.float32 and tr.current.chunks is not None
        assert tr.position.shape == (10, 401) and tr.healthy.dtype == np.uint8 and tr.margins.shape == (10, 5)
        assert int(tr.healthy[()].sum()) == m["splits"]["train"]["healthy"]
        assert np.array_equal(store.split("nominal").K[0], [0, 0, 0, 0, 0, 0, 0.5, 0.5])
        assert store.time.shape == (401,) and store.command.shape == (401,)
        meta = store.metadata
        assert meta["package_version"] and meta["git_revision"] and meta["seeds"]["seed"] == 0
        assert meta["config"]["dataset"]["n_train"] == 10 and meta["fingerprint"] == m["fingerprint"]
        # the rul split lies in the restricted domain
        rul = store.split("rul").K[()]
        assert np.abs(rul[:, [0, 1, 2, 3, 4, 5]]).max() <= 0.1 and np.abs(rul[:, 7] - 0.5).max() <= 0.05
        assert np.all(np.isfinite(tr.current[()]))


def test_rerun_reuses_everything(reference, compose):
    data_dir, _ = reference
    before = _manifest(data_dir)
    metrics, _ = generate(compose("generate", [*TINY, f"data_dir={data_dir}", "stage=merge"]))
    assert metrics["chunks"]["computed"] == 0 and _manifest(data_dir) == before


def test_shards_give_the_same_manifest(reference, compose, tmp_path):
    data_dir = tmp_path / "sharded"
    base = [*TINY, f"data_dir={data_dir}", "shard.count=2"]
    m0, _ = generate(compose("generate", [*base, "shard.index=1"]))
    assert not m0["complete"] and m0["chunks"]["computed"] == 1  # chunk 1 only; 0 and 2 missing
    m1, _ = generate(compose("generate", [*base, "shard.index=0"]))
    assert m1["complete"] and m1["chunks"]["computed"] == 2
    assert _manifest(data_dir) == _manifest(reference[0])


def test_sigkill_then_resume_gives_the_same_manifest(reference, killed_and_resumed):
    data_dir, resumed, _ = killed_and_resumed
    assert resumed.returncode == 0, resumed.stderr
    metrics = json.loads(resumed.stdout)
    assert metrics["chunks"]["reused"] >= 1 and metrics["complete"]
    assert not list((data_dir / "chunks").glob("*.tmp"))  # the stale temp file was removed
    assert _manifest(data_dir) == _manifest(reference[0])


def test_cli_bad_input(killed_and_resumed):
    bad = killed_and_resumed[2]
    assert bad.returncode == 2
    assert bad.stderr.strip().splitlines()[-1].startswith("phm-generate: error: dataset.n_train must be")


def test_corrupt_chunk_is_reported_then_repaired(reference, compose, tmp_path):
    data_dir = tmp_path / "corrupt"
    args = [*TINY, f"data_dir={data_dir}"]
    generate(compose("generate", [*args, "stage=chunks"]))
    with h5py.File(data_dir / "chunks" / "chunk_00001.h5", "r+") as f:  # valid HDF5, wrong content
        f["current"][0, 5] += 1.0
    with pytest.raises(ValueError, match=r"chunk_00001.h5: checksum mismatch.*repair=true"):
        generate(compose("generate", args))
    (data_dir / "chunks" / "chunk_00002.h5").write_bytes(b"not an HDF5 file")
    metrics, _ = generate(compose("generate", [*args, "repair=true"]))
    assert metrics["chunks"]["repaired"] == 2 and metrics["complete"]
    assert _manifest(data_dir) == _manifest(reference[0])


def test_refuses_another_config_unless_overwrite(reference, compose, tmp_path):
    data_dir = tmp_path / "other"
    shutil.copytree(reference[0], data_dir)
    with pytest.raises(ValueError, match="different config.*overwrite=true"):
        generate(compose("generate", [*TINY, f"data_dir={data_dir}", "seed=1"]))
    metrics, _ = generate(compose("generate", [*TINY, f"data_dir={data_dir}", "seed=1", "overwrite=true"]))
    assert metrics["complete"] and metrics["chunks"]["computed"] == N_CHUNKS
    assert _manifest(data_dir)["splits"]["train"]["sha256"] != _manifest(reference[0])["splits"]["train"]["sha256"]


@pytest.mark.parametrize(
    "override, message",
    [
        ("data_dir={file}/sub", "data_dir .* is not writable"),
        ("shard.index=2", "shard.index must be in"),
        ("stage=everything", "stage must be one of"),
        ("assessment.sweep.amplitude=-1", "assessment.sweep.amplitude must be > 0"),
        ("dataset.fidelity=xf", "dataset.fidelity must be"),
        ("dataset.n_labels=-1", r"dataset.n_labels must be an integer >= 0, got -1"),
        ("dataset.n_labels=2.5", r"dataset.n_labels must be an integer >= 0, got 2.5"),
        ("+dataset.label_chunk_size=0", r"dataset.label_chunk_size must be an integer >= 1"),
        ("+dataset.effects.nope={{}}", r"dataset.effects: unknown effect 'nope'"),
        ("+dataset.effects.cogging_torque.amplitude=big", r"dataset.effects.cogging_torque.amplitude must be a number"),
        ("+dataset.randomize.warp_drive.power=[0,1]", r"dataset.randomize: unknown effect 'warp_drive'"),
        ("+dataset.randomize.cogging_torque.amp=[0,1]", r"dataset.randomize.cogging_torque.amp: unknown parameter"),
        (
            "+dataset.randomize.cogging_torque.amplitude=[2,1]",
            r"dataset.randomize.cogging_torque.amplitude must be \[low, high\] with low <= high, got \[2, 1\]",
        ),
        (
            "+dataset.randomize.cogging_torque.phase=[0,1]",
            r"dataset.randomize.cogging_torque: the effect is off in the training model and none of its strength",
        ),
        (
            "+dataset.randomize.cogging_torque.amplitude=[-1,1]",
            r"dataset.randomize.cogging_torque.amplitude: effects.cogging_torque.amplitude must be >= 0",
        ),
    ],
)
def test_bad_generation_input(compose, tmp_path, override, message):
    (tmp_path / "file").write_text("x")
    args = [*TINY, f"data_dir={tmp_path / 'd'}", "shard.count=2", override.format(file=tmp_path / "file")]
    with pytest.raises(ValueError, match=message):
        generate(compose("generate", args))


def test_effects_enter_the_signals_not_the_labels(reference, compose, tmp_path):
    data_dir = tmp_path / "hinge"
    metrics, _ = generate(compose("generate", [*TINY, f"data_dir={data_dir}", "+dataset.effects.aero_hinge_load={}"]))
    assert metrics["fingerprint"] != reference[1]["fingerprint"]  # another store, never reused for the plain one
    with DatasetStore(reference[0]) as plain, DatasetStore(data_dir) as store:
        cfg = OmegaConf.create(store.metadata["config"])
        assert common.plain(cfg.dataset.effects) == {"aero_hinge_load": {}}
        a, b = plain.split("train"), store.split("train")
        assert np.array_equal(a.K[()], b.K[()]) and np.array_equal(a.healthy[()], b.healthy[()])
        k, current = torch.as_tensor(b.K[()]), torch.as_tensor(b.current[()], dtype=torch.float64)
        assert float((current - torch.as_tensor(a.current[()], dtype=torch.float64)).abs().max()) > 0.01
    command = common.command(cfg.command)
    sim = EMASimulator(common.actuator(cfg), "lf", effects={"aero_hinge_load": {}})
    expected = sim.run(k, command, float(command.duration), channels=["current"])["current"]
    torch.testing.assert_close(current, expected, rtol=0, atol=1e-5)


def test_randomized_effects_vary_per_training_record_only(reference, compose, tmp_path):
    """dataset.randomize: each train record carries its own drawn viscous friction (reproduced by simulating
    it alone with that value); nominal, val and rul keep the store's model (here: no effect), as do K."""
    from phm_torch.data import randomization

    data_dir = tmp_path / "randomized"
    cfg = compose(
        "generate", [*TINY, f"data_dir={data_dir}", "+dataset.randomize.viscous_friction.coefficient=[0,2e-4]"]
    )
    metrics, _ = generate(cfg)
    assert metrics["fingerprint"] != reference[1]["fingerprint"]
    with DatasetStore(reference[0]) as plain, DatasetStore(data_dir) as store:
        for split in SPLITS:
            a, b = plain.split(split), store.split(split)
            assert np.array_equal(a.K[()], b.K[()])
            same = np.array_equal(a.current[()], b.current[()])
            assert same == (split != "train"), split
        k = torch.as_tensor(store.split("train").K[()])
        current = torch.as_tensor(store.split("train").current[()], dtype=torch.float64)
        assert "randomize" in store.metadata["seeds"]
    spec = common.build(cfg.dataset, "dataset")
    values = randomization.draw(spec.randomized, len(k), seed_streams(0)["randomize"])[:, 0]
    assert 0 <= values.min() and values.max() <= 2e-4 and values.std() > 3e-5
    command = common.command(cfg.command)
    for row in (0, 7):
        sim = EMASimulator(
            common.actuator(cfg), "lf", effects={"viscous_friction": {"coefficient": float(values[row])}}
        )
        expected = sim.run(k[row : row + 1], command, float(command.duration), channels=["current"])["current"]
        torch.testing.assert_close(current[row : row + 1], expected, rtol=0, atol=1e-5)


def test_datamodule_lazy_deterministic_normalised(reference):
    data_dir, _ = reference

    def first_batch(**kw):
        dm = EMADataModule(data_dir, batch_size=4, seed=3, **kw)
        dm.setup()
        return dm, next(iter(dm.train_dataloader()))

    dm, a = first_batch(y_center="nominal", k_scaling="minmax")
    _, b = first_batch(y_center="nominal", k_scaling="minmax")
    assert all(torch.equal(a[key], b[key]) for key in a)  # same seed, same batches
    assert a["y"].shape == (4, 401) and a["k"].shape == (4, 8) and a["y"].dtype == torch.float32
    with DatasetStore(data_dir) as store:
        tr, nominal = store.split("train"), store.split("nominal").current[0]
        raw = tr.current[sorted(a["index"].tolist())]
        k_raw = tr.K[()]
    order = np.argsort(np.argsort(a["index"].numpy()))
    assert np.allclose(a["y"].numpy(), raw[order] - nominal, atol=1e-6)
    assert a["k"].min() >= 0 and a["k"].max() <= 1
    assert torch.allclose(dm.unscale_k(a["k"]).double(), torch.from_numpy(k_raw[a["index"].numpy()]), atol=1e-6)
    dm_mean, std_batch = first_batch(y_center="mean", y_scale="std", k_scaling="standard")
    n = dm_mean.normalisation
    assert n["y_scale"] > 0 and np.allclose(n["y_center"], tr_mean(data_dir))
    assert abs(float(std_batch["k"][:, 0].mean())) < 3.0 and std_batch["y"].abs().max() < 50.0
    val = next(iter(dm.val_dataloader()))
    assert val["index"].tolist() == [0, 1, 2]  # validation in order
    with pytest.raises(ValueError, match="data.y_center"):
        EMADataModule(data_dir, batch_size=4, y_center="median")
    with pytest.raises(ValueError, match="split 'test'"):
        EMADataModule(data_dir, batch_size=4, val_split="test").setup()


def tr_mean(data_dir: Path) -> np.ndarray:
    with DatasetStore(data_dir) as store:
        return store.split("train").current[()].astype(np.float64).mean(0)


def test_launcher_configs_name_their_plugins():
    plugins = {"local": "joblib", "slurm": "submitit_slurm", "ray_cluster": "ray"}
    for name, plugin in plugins.items():
        assert name != plugin  # a file named as its plugin's config shadows it and includes itself (recursion)
        cfg = yaml.safe_load((CONF_DIR / "hydra" / "launcher" / f"{name}.yaml").read_text())
        assert cfg["defaults"] == [plugin]


@pytest.mark.slow  # 40-100 s on 2 cores
def test_joblib_shards_then_merge(reference, tmp_path):
    pytest.importorskip("hydra_plugins.hydra_joblib_launcher")
    data_dir = tmp_path / "joblib"
    env = {**os.environ, "PYTHONPATH": str(CONF_DIR.parent), "OMP_NUM_THREADS": "1"}
    cmd = [
        sys.executable,
        "-m",
        APP,
        "-m",
        "hydra/launcher=local",
        *TINY,
        f"data_dir={data_dir}",
        "shard.count=2",
        "shard.index=0,1",
        f"hydra.sweep.dir={tmp_path / 'multirun'}",
    ]
    run = subprocess.run(cmd, cwd=tmp_path, env=env, capture_output=True, text=True, timeout=300, check=False)
    assert run.returncode == 0, run.stderr[-2000:]
    if not (data_dir / "manifest.json").exists():  # both shards finished before either saw the other's chunks
        merge = subprocess.run(
            [
                sys.executable,
                "-m",
                APP,
                *TINY,
                f"data_dir={data_dir}",
                "stage=merge",
                f"hydra.run.dir={tmp_path / 'merge'}",
            ],
            cwd=tmp_path,
            env=env,
            capture_output=True,
            text=True,
            timeout=300,
            check=False,
        )
        assert merge.returncode == 0, merge.stderr[-2000:]
    assert _manifest(data_dir) == _manifest(reference[0])


# --- the assessment-only labels split -------------------------------------------------------------------


@pytest.fixture(scope="module")
def labelled(tmp_path_factory, compose):
    """The reference config plus 20 labels, one uninterrupted run: (data_dir, metrics)."""
    data_dir = tmp_path_factory.mktemp("labelled") / "store"
    metrics, _ = generate(compose("generate", [*LABELLED, f"data_dir={data_dir}"]))
    return data_dir, metrics


def test_seed_streams_of_the_signal_splits_are_unchanged_by_labels():
    for seed in (0, 7, 2**40):
        four, three = np.random.SeedSequence(seed).spawn(4), np.random.SeedSequence(seed).spawn(3)
        for a, b in zip(four[:3], three, strict=True):
            assert a.spawn_key == b.spawn_key and np.array_equal(a.generate_state(8), b.generate_state(8))
        streams = seed_streams(seed)
        assert list(streams) == list(STREAMS) and streams["labels"].spawn_key == (3,)
        assert streams["randomize"].spawn_key == (4,)  # added last: the others unchanged
    with pytest.raises(ValueError, match="seed must be"):
        seed_streams(-1)


def test_spec_validates_label_fields():
    base = {
        "n_train": 4,
        "n_val": 0,
        "n_rul": 0,
        "rul_radius": 0.1,
        "uniform": [6],
        "chunk_size": 4,
        "fidelity": "lf",
        "compile": False,
    }
    assert DatasetSpec(**base).n_labels == 0
    for field, bad in (("n_labels", -3), ("n_labels", True), ("n_labels", "10"), ("label_chunk_size", 0)):
        with pytest.raises(ValueError, match=f"dataset.{field} must be an integer"):
            DatasetSpec(**base, **{field: bad})


def test_labels_split_contents(labelled, reference):
    data_dir, metrics = labelled
    assert metrics["complete"] and metrics["chunks"]["computed"] == N_CHUNKS
    assert metrics["label_chunks"] == {"total": 3, "computed": 3, "reused": 0, "repaired": 0}
    assert metrics["labels_per_s"] > 0 and "labels_s" in metrics["timing_s"]
    assert "label_chunks" not in reference[1] and "labels_per_s" not in reference[1]
    m, ref = _manifest(data_dir), _manifest(reference[0])
    assert set(m["splits"]) == {*SPLITS, "labels"} and "labels" not in ref["splits"]
    lab = m["splits"]["labels"]
    assert lab["count"] == 20 and set(lab["sha256"]) == {"K", "healthy", "margins"}
    assert m["label_chunk_size"] == 7 and m["n_label_chunks"] == 3
    assert sorted(p.name for p in (data_dir / "chunks").glob("labels_*.h5")) == [
        "labels_00000.h5",
        "labels_00001.h5",
        "labels_00002.h5",
    ]
    # the signal splits (K, signals, labels) are exactly those of the store without labels
    assert {s: m["splits"][s] for s in SPLITS} == ref["splits"]
    with h5py.File(data_dir / "dataset.h5", "r") as f:
        g = f["labels"]
        assert set(g) == {"K", "healthy", "margins"}
        assert g["K"].shape == (20, 8) and g["K"].dtype == np.float64
        assert g["healthy"].shape == (20,) and g["healthy"].dtype == np.uint8
        assert g["margins"].shape == (20, 5) and g["margins"].dtype == np.float64
        k_lab, k_train = g["K"][()], f["train"]["K"][()]
        assert int(g["healthy"][()].sum()) == lab["healthy"]
    assert np.all((k_lab >= 0) & (k_lab <= 1)) and len(np.unique(k_lab, axis=0)) == 20
    assert not np.isin(k_lab[:, 0], k_train[:, 0]).any()  # an independent stream
    with DatasetStore(data_dir, verify=True) as store:  # verify re-hashes labels too
        view = store.split("labels")
        assert len(view) == 20 and np.array_equal(view.K[()], k_lab)
        with pytest.raises(AttributeError, match="split 'labels' has no array 'current'"):
            _ = view.current
        assert store.metadata["seeds"]["labels"]["spawn_key"] == [3]
    with pytest.raises(ValueError, match="split 'labels' holds no 'current' signals"):
        EMADataModule(data_dir, batch_size=4, train_split="labels").setup()


def test_label_rows_are_the_assessment_of_their_k(labelled, compose):
    data_dir, _ = labelled
    cfg = compose("generate", [*LABELLED, f"data_dir={data_dir}"])
    params = common.actuator(cfg)
    assessment = common.build(cfg.assessment, "assessment", params=params, device=torch.device("cpu"))
    with DatasetStore(data_dir) as store:
        view = store.split("labels")
        rows = [0, 6, 7, 19]  # first and last of chunks 0, 1, 2
        k, healthy, margins = view.K[rows], view.healthy[rows], view.margins[rows]
    res = assessment(torch.as_tensor(k))
    assert np.array_equal(res.healthy.numpy().astype(np.uint8), healthy)
    np.testing.assert_allclose(res.margins.stacked().numpy(), margins, rtol=1e-9, atol=1e-9, equal_nan=True)


def test_labels_resume_and_repair(labelled, compose, tmp_path):
    data_dir = tmp_path / "resume"
    shutil.copytree(labelled[0], data_dir)
    args = [*LABELLED, f"data_dir={data_dir}"]
    for name in ("manifest.json", "dataset.h5", "chunks/labels_00001.h5"):
        (data_dir / name).unlink()
    with h5py.File(data_dir / "chunks" / "labels_00002.h5", "r+") as f:  # valid HDF5, wrong content
        f["margins"][0, 1] += 1.0
    with pytest.raises(ValueError, match=r"labels_00002.h5: checksum mismatch.*repair=true"):
        generate(compose("generate", args))
    metrics, _ = generate(compose("generate", [*args, "repair=true"]))
    assert metrics["chunks"] == {"total": N_CHUNKS, "computed": 0, "reused": N_CHUNKS, "repaired": 0}
    assert metrics["label_chunks"] == {"total": 3, "computed": 2, "reused": 1, "repaired": 1}
    assert _manifest(data_dir) == _manifest(labelled[0])


@pytest.mark.slow  # 40-100 s on 2 cores
def test_labels_shards_give_the_same_manifest(labelled, compose, tmp_path):
    data_dir = tmp_path / "sharded"
    base = [*LABELLED, f"data_dir={data_dir}", "shard.count=2"]
    m1, _ = generate(compose("generate", [*base, "shard.index=1"]))
    assert not m1["complete"] and m1["chunks"]["computed"] == 1 and m1["label_chunks"]["computed"] == 1
    assert sorted(p.name for p in (data_dir / "chunks").glob("labels_*.h5")) == ["labels_00001.h5"]
    m0, _ = generate(compose("generate", [*base, "shard.index=0"]))
    assert m0["complete"] and m0["chunks"]["computed"] == 2 and m0["label_chunks"]["computed"] == 2
    assert _manifest(data_dir) == _manifest(labelled[0])


def test_read_labelled(labelled, reference):
    data_dir = labelled[0]
    with DatasetStore(data_dir) as store:
        k_tr, h_tr = store.split("train").K[()], store.split("train").healthy[()]
        k_lab, h_lab = store.split("labels").K[()], store.split("labels").healthy[()]
    k, h = read_labelled(data_dir)
    assert k.shape == (30, 8) and k.dtype == np.float64 and h.shape == (30,) and h.dtype == bool
    assert np.array_equal(k, np.concatenate([k_tr, k_lab])) and np.array_equal(h, np.concatenate([h_tr, h_lab]) == 1)
    with h5py.File(data_dir / "dataset.h5", "r") as f:  # an open file, other splits
        k2, h2 = read_labelled(f, ("labels", "val"))
    assert k2.shape == (23, 8) and np.array_equal(k2[:20], k_lab) and h2.shape == (23,)
    k3, _ = read_labelled(data_dir / "dataset.h5", ("labels",))
    assert np.array_equal(k3, k_lab)
    k_old, h_old = read_labelled(reference[0])  # a store without labels: train only
    assert np.array_equal(k_old, k_tr) and h_old.shape == (10,)
    with pytest.raises(ValueError, match=r"lacks the split\(s\) \['labels'\]"):
        read_labelled(reference[0], optional=())
    with pytest.raises(ValueError, match=r"lacks the split\(s\) \['test'\]"):
        read_labelled(data_dir, ("train", "test"))
    with pytest.raises(ValueError, match="no dataset store file"):
        read_labelled(data_dir / "nowhere")


def test_empty_splits_are_stored_and_read_as_zero_rows(compose, tmp_path):
    """n_val = n_rul = 0 is allowed: the merged store holds (0, n_e) arrays for them."""
    over = [o for o in TINY if not o.startswith(("dataset.n_val", "dataset.n_rul"))]
    generate(compose("generate", [*over, "dataset.n_val=0", "dataset.n_rul=0", f"data_dir={tmp_path}"]))
    with DatasetStore(tmp_path) as store:
        for split in ("val", "rul"):
            view = store.split(split)
            assert view.K.shape == (0, 8) and view.current.shape[0] == 0
        assert store.split("train").K.shape == (10, 8)


def test_calibrated_sampling_is_recorded_and_cached(compose, tmp_path):
    # dataset.healthy_fraction: a pilot of assessment labels calibrates the sampler; the calibration is in
    # the metrics, the manifest and the metadata, cached in data_dir (a re-run pays no pilot, same store),
    # and the manifest counts the unmeasurable margins of every split.
    over = [o for o in TINY if "healthy_fraction" not in o]
    args = [*over, "+dataset.healthy_fraction=0.5", "+dataset.pilot_size=24", f"data_dir={tmp_path}"]
    metrics, _ = generate(compose("generate", args))
    cal = metrics["sampling"]
    assert cal["pilot_size"] == 24 and cal["healthy_fraction_target"] == 0.5 and cal["pilot_s"] > 0
    assert cal["distance_exponent"] > 0 and not cal["kept_paper"] or cal["distance_exponent"] == 1.0
    manifest = _manifest(tmp_path)
    assert manifest["sampling"] == {k: v for k, v in cal.items() if k != "pilot_s"}
    assert manifest["assessment_sweep"]["frequencies"] == [15.0, 30.0, 60.0, 90.0, 130.0]
    assert manifest["assessment_sweep"]["auto"] == {"frequencies": False, "amplitude": True}
    for split in ("train", "val"):
        entry = manifest["splits"][split]
        assert set(entry["unmeasurable"]) == {"phase_margin", "gain_margin", "bandwidth"}
        assert entry["healthy_fraction"] == pytest.approx(entry["healthy"] / entry["count"], abs=1e-4)
        assert metrics["splits"][split]["unmeasurable"] == entry["unmeasurable"]
    with h5py.File(tmp_path / "dataset.h5", "r") as f:
        margins = f["train"]["margins"][()]
        assert json.loads(f.attrs["metadata"])["sampling"] == manifest["sampling"]
    assert manifest["splits"]["train"]["unmeasurable"]["gain_margin"] == int(np.isnan(margins[:, 3]).sum())
    again, _ = generate(compose("generate", [*args, "stage=merge"]))
    assert again["sampling"]["pilot_s"] == 0 and _manifest(tmp_path) == manifest


@pytest.mark.slow  # 40-100 s on 2 cores
def test_the_pilot_reads_the_same_labels_whatever_its_batch(compose, monkeypatch):
    """An uncompiled pilot is assessed in batches of up to label_chunk_size instead of chunk_size (per vector
    several times cheaper); a label does not depend on its batch, so the calibration is the same (settled labels;
    the refinement's rows are checked alone against a batch in test_assessment)."""
    import dataclasses

    from phm_torch.apps.generate import settings_from_config
    from phm_torch.data import calibration

    over = [o for o in TINY if "max_extensions" not in o and "refine" not in o and "healthy_fraction" not in o]
    cfg = compose(
        "generate",
        [*over, "assessment.sweep.max_extensions=1", "assessment.sweep.refine=0", "+dataset.healthy_fraction=0.5"],
    )
    settings, assessment = settings_from_config(cfg)
    batches: list[list[int]] = []
    records = []
    real = calibration.LabelComputer

    def spy(a, nominal, chunk_size):  # the batch the pilot assesses at
        batches[-1].append(chunk_size)
        return real(a, nominal, chunk_size)

    monkeypatch.setattr(calibration, "LabelComputer", spy)
    for chunk, label_chunk in ((6, 6), (6, 16)):
        batches.append([])
        spec = dataclasses.replace(settings.spec, chunk_size=chunk, label_chunk_size=label_chunk, pilot_size=16)
        records.append(calibration.calibrate_spec(spec, settings.params.nominal_faults, assessment, 3))
    assert batches == [[6], [16]]
    assert records[0] == records[1] and records[0]["pilot_size"] == 16
