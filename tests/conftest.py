"""Shared test fixtures: the default actuator, Hydra config composition, command-line runs."""

from __future__ import annotations

import os
import subprocess
import sys
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from pathlib import Path

import pytest
from omegaconf import DictConfig

from phm_torch.params import CONF_DIR, ActuatorParams, load_actuator

# torch 2.9+ deprecates torch.jit.*; TorchScript stays the design card's format, so the tests that exercise it on
# purpose (marked ``torchscript``) filter exactly that warning, and every other deprecation still shows
TORCHSCRIPT_DEPRECATION = r"ignore:`torch\.jit\.\w+` is deprecated:DeprecationWarning"


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    for item in items:
        if item.get_closest_marker("torchscript") is not None:
            item.add_marker(pytest.mark.filterwarnings(TORCHSCRIPT_DEPRECATION))


REPO_ROOT = Path(__file__).resolve().parent.parent

if os.environ.get("PYTEST_XDIST_WORKER"):  # one torch thread per worker: the workers share the machine's cores
    import torch

    torch.set_num_threads(1)


@pytest.fixture(scope="session")
def params() -> ActuatorParams:
    """The default actuator (conf/actuator/ema_reference.yaml)."""
    return load_actuator()


@contextmanager
def _hydra_context() -> Iterator[None]:
    from hydra import initialize_config_dir
    from hydra.core.global_hydra import GlobalHydra

    GlobalHydra.instance().clear()
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        yield


@pytest.fixture(scope="session")
def compose() -> Callable[..., DictConfig]:
    """compose(config_name, overrides) -> the composed config, as the command line would build it."""
    from hydra import compose as hydra_compose

    from phm_torch.apps.common import keep_choices

    def _compose(config_name: str, overrides: Sequence[str] = ()) -> DictConfig:
        with _hydra_context():  # the actuator/command choices kept, as under the command line
            return keep_choices(
                hydra_compose(config_name=config_name, overrides=list(overrides), return_hydra_config=True)
            )

    return _compose


def _cli_command(module: str, overrides: Sequence[str], run_dir: Path) -> list[str]:
    return [sys.executable, "-m", module, *overrides, f"hydra.run.dir={run_dir}"]


def _cli_env() -> dict[str, str]:
    """The repository importable whether or not it is pip-installed; one thread per (short) run."""
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join(p for p in (str(REPO_ROOT), env.get("PYTHONPATH", "")) if p)
    env.pop("HYDRA_FULL_ERROR", None)
    env.setdefault("OMP_NUM_THREADS", "1")  # several short runs side by side: no thread oversubscription
    return env


@pytest.fixture(scope="session")
def spawn_cli() -> Callable[..., subprocess.Popen]:
    """spawn_cli(module, overrides, cwd) starts a Hydra app as ``python -m module`` (Hydra run directory
    cwd/hydra/<n>) and returns the Popen with text stdout/stderr pipes; start several, then communicate()."""
    counter = iter(range(10**6))

    def _spawn(module: str, overrides: Sequence[str], cwd: Path) -> subprocess.Popen:
        run_dir = Path(cwd) / "hydra" / str(next(counter))
        return subprocess.Popen(
            _cli_command(module, overrides, run_dir),
            cwd=cwd,
            env=_cli_env(),
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
        )

    return _spawn


@pytest.fixture
def run_cli(tmp_path: Path) -> Callable[..., subprocess.CompletedProcess]:
    """run_cli(module, *overrides) runs a Hydra app to completion in a subprocess with cwd = tmp_path."""

    def _run(module: str, *overrides: str, timeout: float = 120) -> subprocess.CompletedProcess:
        return subprocess.run(
            _cli_command(module, overrides, tmp_path / "hydra"),
            cwd=tmp_path,
            env=_cli_env(),
            capture_output=True,
            text=True,
            timeout=timeout,
            check=False,
        )

    return _run


# Fault vectors of the reference actuator simulated once per session, HF, on its full chirp: test_physics' cases
# (the datasheet's fault signatures) and test_pretrained's fresh records share one batch, because an HF run costs
# nearly as much for 4 rows as for 14 (its time steps, not its batch, set the cost).
_NOMINAL = (0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.5, 0.5)


def _faults(**kw: float) -> tuple[float, ...]:
    k = list(_NOMINAL)
    for name, v in kw.items():
        k[int(name[1:]) - 1] = v
    return tuple(k)


HF_CHIRP_FAULTS = (
    _NOMINAL,
    *(_faults(**{f"k{i}": 1.0}) for i in range(1, 7)),
    _faults(k6=1.0, k7=0.0),
    _faults(k8=1.0),
    _faults(k8=0.0),
    _faults(k1=0.3),
    _faults(k3=0.4),
    _faults(k2=0.2, k8=0.7),
)


@pytest.fixture(scope="session")
def hf_reference_chirp(
    tmp_path_factory: pytest.TempPathFactory,
) -> Callable[[Sequence[Sequence[float]]], dict[str, object]]:
    """select(k) -> the HF records of fault vectors k (each one of HF_CHIRP_FAULTS) on the reference actuator's
    chirp: ``{"time": (n,), channel: (len(k), n)}`` for every channel, from one simulation per test run: the
    first xdist worker to ask simulates (~100 s) and saves it, the others wait for the file and load it."""
    import torch
    from filelock import FileLock

    from phm_torch.command import Chirp
    from phm_torch.simulator import EMASimulator

    shared = tmp_path_factory.getbasetemp()
    if os.environ.get("PYTEST_XDIST_WORKER"):
        shared = shared.parent  # the run's directory, above every worker's own
    path = shared / "hf_reference_chirp.pt"
    with FileLock(str(path) + ".lock"):
        if not path.exists():
            command = Chirp()
            rows = torch.tensor(HF_CHIRP_FAULTS, dtype=torch.float64)
            run = EMASimulator(load_actuator(), "hf").run(rows, command, command.duration)
            torch.save({"time": run.time, **run.channels}, path.with_suffix(".tmp"))
            path.with_suffix(".tmp").replace(path)
        saved = torch.load(path, weights_only=True)

    def select(k: Sequence[Sequence[float]]) -> dict[str, object]:
        index = [HF_CHIRP_FAULTS.index(tuple(float(v) for v in row)) for row in k]
        return {"time": saved["time"]} | {c: v[index] for c, v in saved.items() if c != "time"}

    return select
