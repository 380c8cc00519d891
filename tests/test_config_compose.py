"""Every app's config composes and every node with a ``_target_`` instantiates.

Each primary config (``conf/<app>.yaml``) is composed with Hydra's compose API, once with its default choices
and once for the second shipped actuator and its test command; then every node that names a ``_target_`` is
instantiated (recursively, so its nested targets too). A node whose constructor takes objects the app passes
at run time (the actuator's datasheet, a device, the nominal fault vector) gets them from :data:`RUNTIME`.
A failure names the app, the overrides and the node's path.
"""

from __future__ import annotations

import importlib
import inspect
from collections.abc import Iterator
from typing import Any

import pytest
from hydra import compose, initialize_config_dir
from hydra.core.global_hydra import GlobalHydra
from hydra.utils import get_class, get_method, instantiate
from omegaconf import DictConfig, ListConfig, OmegaConf

from phm_torch.apps import schema
from phm_torch.params import CONF_DIR, ActuatorParams, load_actuator

APPS = sorted(p.stem for p in CONF_DIR.glob("*.yaml"))
VARIANTS = {
    "defaults": [],
    "rudder": ["actuator=ema_hvdc_rudder", "command=chirp_hvdc_rudder"],
    "flap": ["actuator=ema_115v_flap", "command=chirp_115v_flap"],
}


def runtime(cfg: DictConfig) -> dict[str, Any]:
    """The run-time objects the apps pass to constructors, by parameter name."""
    node = cfg.get("actuator")
    params = (
        load_actuator() if node is None else ActuatorParams.from_mapping(OmegaConf.to_container(node, resolve=True))
    )
    return {"params": params, "device": "cpu", "nominal": list(params.nominal_faults)}


def target_nodes(node: Any, path: str = "") -> Iterator[tuple[str, DictConfig]]:
    """(dotted path, node) of every node below ``node`` (itself included) that has a ``_target_``."""
    if isinstance(node, DictConfig):
        if "_target_" in node:
            yield path or "<root>", node
        for key in node:
            yield from target_nodes(node._get_node(key), f"{path}.{key}" if path else str(key))
    elif isinstance(node, ListConfig):
        for i in range(len(node)):
            yield from target_nodes(node._get_node(i), f"{path}[{i}]")


def required_runtime(node: DictConfig, available: dict[str, Any]) -> dict[str, Any]:
    """The run-time arguments ``node``'s target requires that the node does not set."""
    target = node["_target_"]
    try:
        call = get_class(target)
    except (ImportError, ValueError):
        call = get_method(target)
    params = inspect.signature(call).parameters.values()
    missing = [
        p.name
        for p in params
        if p.default is inspect.Parameter.empty
        and p.kind in (p.POSITIONAL_OR_KEYWORD, p.KEYWORD_ONLY)
        and p.name not in node
    ]
    return {name: available[name] for name in missing if name in available}


def composed(app: str, overrides: list[str]) -> DictConfig:
    for entry in OmegaConf.load(CONF_DIR / f"{app}.yaml").get("defaults", []):
        if isinstance(entry, str) and entry.startswith(f"/{schema.GROUP}/"):  # code defaults (apps/schema.py),
            importlib.import_module(f"phm_torch.apps.{entry.split('/')[2].split('@')[0]}")  # registered by the app
    GlobalHydra.instance().clear()
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        return compose(config_name=app, overrides=overrides)


@pytest.mark.parametrize("variant", sorted(VARIANTS))
@pytest.mark.parametrize("app", APPS)
def test_every_target_node_of_every_app_config_instantiates(app, variant):
    overrides = VARIANTS[variant]
    cfg = composed(app, overrides)
    available = runtime(cfg)
    failures, count = [], 0
    for path, node in target_nodes(cfg):
        count += 1
        try:  # objects passed after instantiation, as the apps do (common.build): Hydra would copy them into config
            instantiate(node, _partial_=True)(**required_runtime(node, available))
        except Exception as e:  # noqa: BLE001 (any failure is reported with the node path, every node checked)
            failures.append(
                f"conf/{app}.yaml {' '.join(overrides)}: {path} ({node['_target_']}): {type(e).__name__}: {e}"
            )
    assert not failures, "\n".join(failures)
    if app in ("generate", "train", "workbench", "fit_lf"):
        assert count > 0, f"conf/{app}.yaml: no _target_ node found"


def _leaves(node: Any, path: str = "") -> Iterator[tuple[str, Any]]:
    if isinstance(node, dict):
        for key, value in node.items():
            yield from _leaves(value, f"{path}.{key}" if path else str(key))
    else:
        yield path, node


def test_a_yaml_composing_code_defaults_does_not_restate_them():
    """A config that composes a tree of code defaults (``- /schema/<name>@_here_``) sets only values that differ."""
    from hydra.core.config_store import ConfigStore

    repo = ConfigStore.instance().repo
    checked, restated = [], []
    for path in sorted(CONF_DIR.rglob("*.yaml")):
        data = OmegaConf.to_container(OmegaConf.load(path), resolve=False)
        if not isinstance(data, dict):
            continue
        for entry in data.get("defaults", []):
            if not (isinstance(entry, str) and entry.startswith(f"/{schema.GROUP}/")):
                continue
            *groups, leaf = entry.lstrip("/").split("@")[0].split("/")
            if groups == [schema.GROUP]:  # an app's own tree, registered by the app (commands: by phm_torch.apps)
                importlib.import_module(f"phm_torch.apps.{leaf}")
            node = repo
            for group in groups:
                node = node[group]
            tree = OmegaConf.to_container(node[f"{leaf}.yaml"].node)
            defaults = dict(_leaves(tree))
            checked.append(path.name)
            restated += [
                f"{path.relative_to(CONF_DIR)}: {key} = {value!r} is the code default"
                for key, value in _leaves({k: v for k, v in data.items() if k != "defaults"})
                if key != "_target_" and key in defaults and defaults[key] == value
            ]
    assert {"workbench.yaml", "track.yaml", "chirp.yaml", "sine.yaml"} <= set(checked), checked
    assert not restated, "\n".join(restated)
