"""Scale-out exercised, not only configured (docs/scale_out.md).

* phm-generate's shards through Hydra's Ray launcher, on a new local Ray instance and on a running Ray
  cluster joined by its address, and through Hydra's submitit launcher with its local executor: the same
  manifest (fingerprint, per-split counts, the SHA-256 of every array) as the single-process run;
* phm-train's Adam FDI under Lightning DDP (``strategy=ddp``, 2 CPU processes, gloo): the err_k of the
  single-process run within its 95 % interval; stopped by ``max_steps`` at a checkpoint and resumed from
  it, the same network as the uninterrupted DDP run, bit for bit.

The launchers are the ``scaleout`` extra (``pip install -e '.[scaleout]'``); their tests skip without it.
Each multi-process run starts Python processes that import torch (and a Ray instance): slow tests.
"""

from __future__ import annotations

import json
import re
import shutil
import socket
import subprocess
import tempfile
import time
from pathlib import Path

import lightning as L
import pytest
import torch
from hydra import compose as hydra_compose
from hydra import initialize_config_dir
from hydra.core.global_hydra import GlobalHydra
from surrogate_data import write_store
from test_dataset import TINY
from test_fdi import teacher_data
from test_train import QUICK

from phm_torch.apps.generate import generate
from phm_torch.apps.train import train_surrogates
from phm_torch.params import CONF_DIR
from phm_torch.surrogates import FDIMLP
from phm_torch.surrogates.lightning_fdi import FDIModule, KeepBest

GENERATE = "phm_torch.apps.generate"
TRAIN = "phm_torch.apps.train"
SCALEOUT = "the scale-out extra is not installed: pip install -e '.[scaleout]'"
# the Adam FDI of the DDP tests: 3 optimiser steps an epoch on one process (380 rows, batches of 128)
ADAM = (*QUICK, "model=fdi_adam", "model.fit.max_epochs=100", "threads=1")
# DDP on 2 processes: half the batch per process, so the same effective batch and steps an epoch
DDP = ("trainer.strategy=ddp", "trainer.devices=2", "trainer.accelerator=cpu", "model.fit.batch_size=64")
STOP_STEPS = 90  # run A stops after epoch 30 of 100 (3 steps an epoch)


def _ray() -> None:
    pytest.importorskip("ray", reason=SCALEOUT)
    pytest.importorskip("hydra_plugins.hydra_ray_launcher", reason=SCALEOUT)


def _manifest(data_dir: Path) -> dict:
    return json.loads((data_dir / "manifest.json").read_text())


def _finish(proc: subprocess.Popen, timeout: float = 600) -> subprocess.CompletedProcess:
    out, err = proc.communicate(timeout=timeout)
    assert proc.returncode == 0, err[-3000:]
    return subprocess.CompletedProcess(proc.args, proc.returncode, out, err)


def _sharded(spawn_cli, cwd: Path, launcher: list[str]) -> tuple[Path, subprocess.CompletedProcess]:
    """Two shards of the tiny store through ``launcher`` (then stage=merge if no shard saw every chunk at
    its end); returns the store directory and the launcher run."""
    data_dir = cwd / "store"
    run = _finish(
        spawn_cli(
            GENERATE,
            [
                "-m",
                *TINY,
                f"data_dir={data_dir}",
                "shard.count=2",
                "shard.index=0,1",
                f"hydra.sweep.dir={cwd / 'multirun'}",
                *launcher,
            ],
            cwd,
        )
    )
    for shard in (0, 1):  # each shard ran as a Hydra job of the sweep
        assert (cwd / "multirun" / f"shard{shard}" / "generate.log").is_file()
    if not (data_dir / "manifest.json").exists():
        _finish(spawn_cli(GENERATE, [*TINY, f"data_dir={data_dir}", "stage=merge"], cwd))
    return data_dir, run


@pytest.fixture(scope="module")
def reference(tmp_path_factory, compose) -> dict:
    """The manifest of the single-process tiny store."""
    data_dir = tmp_path_factory.mktemp("single") / "store"
    generate(compose("generate", [*TINY, f"data_dir={data_dir}"]))
    return _manifest(data_dir)


def _launcher_config(app: str, overrides: list[str]):
    """The composed config of ``app`` with its ``hydra`` node (the launcher's settings)."""
    GlobalHydra.instance().clear()
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        return hydra_compose(app, overrides, return_hydra_config=True)


def test_ray_cluster_config():
    _ray()
    cfg = _launcher_config("generate", ["hydra/launcher=ray_cluster"])
    launcher = cfg.hydra.launcher
    assert launcher._target_ == "hydra_plugins.hydra_ray_launcher.ray_launcher.RayLauncher"
    # local: a new instance even where a cluster runs; no object-store size, which ray.init refuses
    # when it joins a cluster (the plugin's default sets one)
    assert launcher.ray.init.address == "local" and launcher.ray.init.object_store_memory is None
    assert launcher.ray.remote.num_cpus == cfg.threads == 1  # a shard reserves the cores its threads use


def test_slurm_config():
    """The SLURM recipe composes (it is not run here: no SLURM cluster); the partition is the user's."""
    pytest.importorskip("hydra_plugins.hydra_submitit_launcher", reason=SCALEOUT)
    cfg = _launcher_config("generate", ["hydra/launcher=slurm", "hydra.launcher.partition=cpu", "threads=4"])
    launcher = cfg.hydra.launcher
    assert launcher._target_ == "hydra_plugins.hydra_submitit_launcher.submitit_launcher.SlurmLauncher"
    assert launcher.partition == "cpu" and launcher.cpus_per_task == cfg.threads == 4


@pytest.mark.slow
def test_ray_shards_on_a_local_instance(reference, spawn_cli, tmp_path):
    _ray()
    data_dir, run = _sharded(spawn_cli, tmp_path, ["hydra/launcher=ray_cluster", "+hydra.launcher.ray.init.num_cpus=2"])
    assert "Started a local Ray instance" in run.stderr
    assert (
        len(set(re.findall(r"\(_run_job pid=(\d+)\)", run.stdout + run.stderr))) >= 1
    )  # the shards' output, from Ray workers
    assert _manifest(data_dir) == reference


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.mark.slow
def test_ray_shards_on_a_running_cluster(reference, spawn_cli, tmp_path, monkeypatch):
    """The multi-node recipe on one node: `ray start --head`, then the launcher joins it by address."""
    _ray()
    ray_cli = shutil.which("ray")
    if ray_cli is None:
        pytest.skip("the ray command is not on PATH")
    monkeypatch.setenv("RAY_AUTH_MODE", "token")  # an explicit address does not turn Ray's token auth on
    port = _free_port()
    with tempfile.TemporaryDirectory(prefix="ray") as temp:  # short: Ray's socket paths must fit 107 bytes
        head_log = Path(temp) / "head.log"
        with open(head_log, "w") as log:
            # its own temp dir: the head's address file stays out of /tmp/ray (address=auto elsewhere)
            head = subprocess.Popen(
                [
                    ray_cli,
                    "start",
                    "--head",
                    "--block",
                    f"--port={port}",
                    "--node-ip-address=127.0.0.1",
                    "--num-cpus=2",
                    "--include-dashboard=false",
                    "--disable-usage-stats",
                    f"--temp-dir={temp}",
                ],
                stdout=log,
                stderr=subprocess.STDOUT,
            )
        try:
            deadline = time.monotonic() + 180
            while "block forever" not in head_log.read_text() and head.poll() is None:
                assert time.monotonic() < deadline, head_log.read_text()[-2000:]
                time.sleep(0.5)
            assert head.poll() is None, head_log.read_text()[-2000:]
            data_dir, run = _sharded(
                spawn_cli, tmp_path, ["hydra/launcher=ray_cluster", f"hydra.launcher.ray.init.address=127.0.0.1:{port}"]
            )
        finally:
            head.terminate()  # --block: the head stops its Ray processes on SIGTERM
            head.wait(timeout=120)
    assert "Connected to Ray cluster" in run.stderr and "Started a local Ray instance" not in run.stderr
    assert _manifest(data_dir) == reference


@pytest.mark.slow
def test_submitit_local_shards(reference, spawn_cli, tmp_path):
    pytest.importorskip("hydra_plugins.hydra_submitit_launcher", reason=SCALEOUT)
    data_dir, _ = _sharded(spawn_cli, tmp_path, ["hydra/launcher=submitit_local", "hydra.launcher.timeout_min=20"])
    jobs = sorted((tmp_path / "multirun" / ".submitit").glob("*/*_result.pkl"))
    assert len(jobs) == 2  # two submitit jobs, one per shard
    assert _manifest(data_dir) == reference


# --- phm-train under Lightning DDP --------------------------------------------------------------------------


@pytest.fixture(scope="module")
def store(tmp_path_factory) -> Path:
    return write_store(tmp_path_factory.mktemp("store"), {"train": 400, "val": 100}, noise=0.01)


@pytest.fixture(scope="module")
def single(store, compose, tmp_path_factory) -> dict:
    out = tmp_path_factory.mktemp("single_train")
    metrics, _ = train_surrogates(compose("train", [f"data_dir={store}", f"out_dir={out}", *ADAM]))
    return metrics


def _ddp(spawn_cli, store: Path, cwd: Path, *extra: str) -> tuple[dict, dict, str]:
    """A DDP phm-train run: (metrics.json, predictions.pt, stderr)."""
    out_dir = cwd / "out"
    cwd.mkdir(parents=True, exist_ok=True)
    run = _finish(spawn_cli(TRAIN, [f"data_dir={store}", f"out_dir={out_dir}", *ADAM, *DDP, *extra], cwd))
    predictions = torch.load(out_dir / "predictions.pt", weights_only=True)
    return json.loads((out_dir / "metrics.json").read_text()), predictions, run.stderr


@pytest.fixture(scope="module")
def ddp(store, spawn_cli, tmp_path_factory) -> tuple[dict, dict, str]:
    if not torch.distributed.is_available():
        pytest.skip("this torch build has no torch.distributed")
    return _ddp(spawn_cli, store, tmp_path_factory.mktemp("ddp"))


@pytest.mark.slow
def test_ddp_reaches_the_single_process_err_k(single, ddp):
    metrics, _, stderr = ddp
    assert "distributed_backend=gloo" in stderr and "Starting with 2 processes" in stderr
    assert metrics["epochs_run"] == single["epochs_run"] == 100
    lo, hi = single["err_k_ci95"]
    assert lo <= metrics["err_k"] <= hi, (metrics["err_k"], single["err_k"], (lo, hi))


@pytest.mark.slow
def test_ddp_resumes_from_a_checkpoint(store, ddp, spawn_cli, tmp_path):
    _ddp(spawn_cli, store, tmp_path / "a", f"+trainer.max_steps={STOP_STEPS}")  # stopped after epoch 30
    ckpt = torch.load(tmp_path / "a" / "out" / "checkpoints" / "last.ckpt", weights_only=True)
    assert (ckpt["epoch"], ckpt["global_step"]) == (STOP_STEPS // 3 - 1, STOP_STEPS)
    metrics, predictions, stderr = _ddp(
        spawn_cli, store, tmp_path / "b", f"ckpt_path={tmp_path / 'a' / 'out' / 'checkpoints' / 'last.ckpt'}"
    )
    assert "Restored all states from the checkpoint" in stderr
    # DistributedSampler orders each epoch by (seed, epoch) and the checkpoint holds the optimiser, the
    # cosine schedule and the callbacks' state: the resumed run ends where the uninterrupted one does
    full_metrics, full_predictions, _ = ddp
    assert metrics["err_k"] == full_metrics["err_k"] and metrics["best_epoch"] == full_metrics["best_epoch"]
    assert torch.equal(predictions["k_hat"], full_predictions["k_hat"])


def test_keep_best_travels_in_the_checkpoint(tmp_path):
    """The best epoch's weights (KeepBest) are in Lightning's checkpoint: a resumed run still returns them,
    even when the interruption came after that epoch."""
    x, y = teacher_data(200, 0)
    xv, yv = teacher_data(50, 1)
    torch.manual_seed(0)
    keep = KeepBest()
    trainer = L.Trainer(
        max_epochs=4,
        logger=False,
        enable_progress_bar=False,
        enable_model_summary=False,
        callbacks=[keep, L.pytorch.callbacks.ModelCheckpoint(tmp_path, save_last=True)],
        default_root_dir=tmp_path,
        accelerator="cpu",
    )
    trainer.fit(
        FDIModule(FDIMLP(6, 12).set_normalization(x), lr=1e-2),
        torch.utils.data.DataLoader(torch.utils.data.TensorDataset(x, y), batch_size=64),
        torch.utils.data.DataLoader(torch.utils.data.TensorDataset(xv, yv), batch_size=50),
    )
    saved = torch.load(tmp_path / "last.ckpt", weights_only=True)["callbacks"]["KeepBest"]
    assert keep.best_epoch >= 0 and (saved["best"], saved["best_epoch"]) == (keep.best, keep.best_epoch)
    resumed = KeepBest()
    resumed.load_state_dict(saved)
    fresh = FDIModule(FDIMLP(6, 12).set_normalization(x))
    resumed.restore(fresh)
    assert all(torch.equal(fresh.network.state_dict()[k], v) for k, v in keep.state.items())
