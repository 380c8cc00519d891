"""Shared pieces of the Hydra entry points: config validation, noise, metrics, error reporting.

Every validator raises :class:`ValueError` naming the config field, so that the command line can print
one clear line (see :func:`report_errors`).
"""

from __future__ import annotations

import functools
import math
import os
import sys
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch
from hydra.errors import HydraException, InstantiationException
from hydra.utils import instantiate
from omegaconf import DictConfig, ListConfig, OmegaConf
from omegaconf.errors import OmegaConfBaseException

from .. import provenance
from ..checks import build, device, integer, number  # noqa: F401  (the apps call them as common.*)
from ..effects import Effect, build_effects
from ..faults import FAULT_NAMES, N_FAULTS, as_fault_tensor
from ..io.atomic import write_json  # noqa: F401  (common.write_json: the apps write their JSON with it)
from ..params import CONF_DIR, ActuatorParams
from ..simulator import MOTORS

CONFIG_PATH = str(CONF_DIR)

# Errors that are the user's input, reported as one line instead of a traceback.
USER_ERRORS = (ValueError, OmegaConfBaseException, HydraException)


def plain(node: Any) -> Any:
    """A resolved plain-Python copy of a config node (or the value itself)."""
    if isinstance(node, (DictConfig, ListConfig)):
        return OmegaConf.to_container(node, resolve=True)
    return node


def fault_vector(value: Any, name: str = "faults") -> list[float]:
    """Validate one fault vector k1..k8 in [0, 1]; the message names the entry (``faults[2] (k3, short_a)``)."""
    value = plain(value)
    if not isinstance(value, (list, tuple)):
        raise ValueError(f"{name} must be a list of {N_FAULTS} numbers k1..k{N_FAULTS} in [0, 1], got {value!r}")
    if len(value) != N_FAULTS:
        raise ValueError(f"{name} must have {N_FAULTS} entries (k1..k{N_FAULTS}), got {len(value)}: {value!r}")
    out = []
    for i, v in enumerate(value):
        label = f"{name}[{i}] (k{i + 1}, {FAULT_NAMES[i]})"
        if isinstance(v, bool) or not isinstance(v, (int, float)):
            raise ValueError(f"{label} must be a number, got {v!r}")
        if not math.isfinite(v):
            raise ValueError(f"{label} is not finite: {v!r}")
        if not 0.0 <= v <= 1.0:
            raise ValueError(f"{label} = {v!r} is outside [0, 1]")
        out.append(float(v))
    as_fault_tensor(out)  # the simulator's own check, kept in step
    return out


def actuator(cfg: DictConfig) -> ActuatorParams:
    """The ``actuator`` node as validated :class:`ActuatorParams` (every error message starts ``actuator``)."""
    try:
        return ActuatorParams.from_mapping(plain(cfg.actuator))
    except (ValueError, TypeError) as e:
        if str(e).startswith("actuator"):
            raise
        raise ValueError(f"actuator: {e}") from None


CHOICES = "choices"  # where a config composed by phm-run keeps its config-group choices (see choice)


def keep_choices(cfg: DictConfig, keys: tuple[str, ...] = provenance.KEYS) -> DictConfig:
    """A config composed with ``return_hydra_config=True`` without its ``hydra`` node, the config-group choices
    of ``keys`` kept under ``choices`` (what :func:`choice` reads outside ``@hydra.main``)."""
    from omegaconf import open_dict

    choices = {k: cfg.hydra.runtime.choices.get(k) for k in keys}
    with open_dict(cfg):
        del cfg["hydra"]
        cfg[CHOICES] = choices
    return cfg


def choice(cfg: DictConfig, key: str) -> str | None:
    """The config-group option chosen for ``key`` (``actuator=<name>``) in this app, or ``None``.

    Under ``@hydra.main`` (and inside ``phm-run``, which passes its own choice to every stage) Hydra's
    runtime choices say it; outside (a composed config in a test or a notebook) the shipped config with the
    same values names it, else ``None``.
    """
    from hydra.core.hydra_config import HydraConfig

    if cfg.get(key) is None:
        return None
    kept = (cfg.get(CHOICES) or {}).get(key)
    if kept:
        return str(kept)
    if HydraConfig.initialized():
        name = HydraConfig.get().runtime.choices.get(key)
        if name:
            return str(name)
    return None


def requested_provenance(cfg: DictConfig) -> dict[str, Any]:
    """``{"actuator", "command"}`` records of what ``cfg`` chose (``None`` where its node is null or absent)."""
    names = {key: choice(cfg, key) for key in provenance.KEYS}
    config: dict[str, Any] = {}
    if cfg.get("actuator") is not None:
        config["actuator"] = provenance.actuator_values(actuator(cfg))
    if cfg.get("command") is not None:
        command(cfg.command)  # validated before it is recorded
        config["command"] = plain(cfg.command)
    return provenance.from_config(config, names)


def reconcile_provenance(cfg: DictConfig, recorded: Mapping[str, Any] | None, where: str) -> dict[str, Any]:
    """The actuator and command records an app consuming an artefact uses (see :func:`provenance.reconcile`):
    an explicit ``actuator=``/``command=`` must match the artefact's record, else the artefact's is adopted."""
    requested = requested_provenance(cfg)
    recorded = recorded or {}
    return {
        key: provenance.reconcile(recorded.get(key), requested[key], cfg.get(key) is not None, key, where)
        for key in provenance.KEYS
    }


def actuator_of(record: Mapping[str, Any] | None, cfg: DictConfig) -> ActuatorParams:
    """The actuator of a provenance record, or of ``cfg`` when there is none (an artefact without provenance)."""
    if record is not None:
        return ActuatorParams.from_mapping(record["values"])
    if cfg.get("actuator") is None:
        raise ValueError("actuator: the artefact records no actuator; choose one with actuator=<name>")
    return actuator(cfg)


def fidelity(value: Any) -> str:
    if value not in MOTORS:
        raise ValueError(f"fidelity must be one of {sorted(MOTORS)}, got {value!r}")
    return str(value)


def set_threads(cfg: DictConfig) -> None:
    """Apply ``cfg.threads`` (torch intra-op threads; absent or null leaves torch's setting alone)."""
    threads = cfg.get("threads")
    if threads is not None:
        torch.set_num_threads(integer(threads, "threads", 1))


def effects(value: Any, params: ActuatorParams | None = None) -> list[Effect]:
    """Instantiate the ``effects`` mapping (``{name: {param: value}}``); unknown names are errors. With the
    actuator ``params``, shape parameters sized by it default to their typical magnitude there."""
    spec = plain(value) or {}
    if not isinstance(spec, Mapping):
        raise ValueError(f"effects must be a mapping {{name: {{param: value}}}}, got {spec!r}")
    for key, values in spec.items():
        if values is not None and not isinstance(values, Mapping):
            raise ValueError(
                f"effects.{key} must be a mapping of parameters (e.g. +effects.{key}={{}}), got {values!r}"
            )
    return build_effects(spec, params)


def command(node: Any) -> Callable[[torch.Tensor], torch.Tensor]:
    """Instantiate the ``command`` node; a constructor error is reported as ``command: ...``."""
    try:
        return instantiate(node)
    except InstantiationException as e:
        cause = e.__cause__ if e.__cause__ is not None else e
        raise ValueError(f"command: {cause}") from None


@dataclass
class SimulationSettings:
    """The validated simulation inputs shared by ``phm-simulate`` and ``phm-cases``."""

    params: ActuatorParams
    fidelity: str
    command: Callable[[torch.Tensor], torch.Tensor]
    duration: float
    seed: int
    noise: dict[str, float]
    effects: list[Effect]
    device: torch.device


def simulation_settings(cfg: DictConfig) -> SimulationSettings:
    """Validate the actuator, fidelity, command, duration, seed, noise, effects and device of ``cfg``."""
    params = actuator(cfg)
    fid = fidelity(cfg.fidelity)
    cmd = command(cfg.command)
    dur = number(cfg.duration, "duration", 0.0, strict=True)  # the YAML's default: ${command.duration}
    return SimulationSettings(
        params,
        fid,
        cmd,
        dur,
        integer(cfg.seed, "seed", 0),
        noise(cfg),
        effects(cfg.effects, params),
        device(cfg.device),
    )


def noise(cfg: DictConfig) -> dict[str, float]:
    """Noise standard deviations by channel, validated (>= 0)."""
    node = plain(cfg.noise) or {}
    channels = ("current", "position")
    unknown = sorted(set(node) - set(channels))
    if unknown:
        raise ValueError(f"noise: unknown channel(s) {unknown}; known: {list(channels)}")
    missing = [ch for ch in channels if ch not in node]
    if missing:
        raise ValueError(f"noise: no standard deviation for {missing} (0.0: no noise)")
    return {ch: number(node[ch], f"noise.{ch}", 0.0) for ch in channels}


def signal_metrics(channels: Mapping[str, torch.Tensor]) -> dict[str, list[float]]:
    """Per-run tracking error RMS/max [rad], peak current [A] and peak motor speed [rad/s] of (B, n) channels."""
    err = channels["command"] - channels["position"]
    return {
        "tracking_error_rms": err.pow(2).mean(-1).sqrt().tolist(),
        "tracking_error_max": err.abs().amax(-1).tolist(),
        "peak_current": channels["current"].abs().amax(-1).tolist(),
        "peak_speed": channels["speed"].abs().amax(-1).tolist(),
    }


def hydra_output_dir() -> Path | None:
    """The Hydra run directory when running under ``@hydra.main``, else ``None``."""
    from hydra.core.hydra_config import HydraConfig

    if not HydraConfig.initialized():
        return None
    return Path(HydraConfig.get().runtime.output_dir)


def report_errors(prog: str) -> Callable[[Callable[..., Any]], Callable[..., Any]]:
    """Decorator for a Hydra task function: a user error prints ``prog: error: <message>`` on stderr and
    exits with status 2, without a traceback (set HYDRA_FULL_ERROR=1 to get the traceback)."""

    def wrap(func: Callable[..., Any]) -> Callable[..., Any]:
        @functools.wraps(func)
        def inner(*args: Any, **kwargs: Any) -> Any:
            try:
                return func(*args, **kwargs)
            except USER_ERRORS as e:
                if os.environ.get("HYDRA_FULL_ERROR") == "1":
                    raise
                print(f"{prog}: error: {e}", file=sys.stderr, flush=True)
                raise SystemExit(2) from None

        return inner

    return wrap
