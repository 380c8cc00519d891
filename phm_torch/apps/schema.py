"""Code defaults as config nodes, so that a value set in code is not restated in YAML.

A settings dataclass is the single home of its defaults. :func:`node` turns an instance into the config node
that instantiates it (``_target_`` plus every field); an app gathers such nodes into its tree of code
defaults and :func:`register`\\ s it in Hydra's ConfigStore (group ``schema``). The app's YAML composes the
tree in first (``- /schema/<app>@_here_`` in its defaults list) and then sets only what differs, so every
value is still in the composed config: overridable on the command line without ``+`` (``score.alpha=0.05``),
printed by ``--cfg job`` and kept in the run's ``.hydra/config.yaml``.

The tree is registered when the app's module is imported: compose such a config after importing its app
(``import phm_torch.apps.workbench``), as ``phm-run`` and the tests do. The test commands' defaults, which
every app's ``command`` group uses, are registered by ``phm_torch.apps`` itself (:func:`register_commands`).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import MISSING, fields, is_dataclass
from typing import Any

from hydra.core.config_store import ConfigStore

GROUP = "schema"


def node(settings: Any) -> dict[str, Any]:
    """The config node of a settings dataclass instance: its class as ``_target_`` and every init field's value
    (a nested dataclass as its own node, tuples as lists)."""
    if not is_dataclass(settings) or isinstance(settings, type):
        raise ValueError(f"node: a dataclass instance is required, got {settings!r}")
    cls = type(settings)
    return {
        "_target_": f"{cls.__module__}.{cls.__qualname__}",
        **{f.name: plain(getattr(settings, f.name)) for f in fields(settings) if f.init},
    }


def plain(value: Any) -> Any:
    """``value`` as config data: dataclass instances as nodes, mappings as dicts, tuples as lists."""
    if is_dataclass(value) and not isinstance(value, type):
        return node(value)
    if isinstance(value, Mapping):
        return {str(k): plain(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [plain(v) for v in value]
    return value


def class_defaults(cls: type) -> dict[str, Any]:
    """The config node of a dataclass's defaults: ``_target_`` and the init fields that have a default (the ones
    without stay the YAML's to set)."""
    if not is_dataclass(cls) or not isinstance(cls, type):
        raise ValueError(f"class_defaults: a dataclass is required, got {cls!r}")
    out: dict[str, Any] = {"_target_": f"{cls.__module__}.{cls.__qualname__}"}
    for f in fields(cls):
        if f.init and f.default is not MISSING:
            out[f.name] = plain(f.default)
        elif f.init and f.default_factory is not MISSING:
            out[f.name] = plain(f.default_factory())
    return out


def register_commands() -> None:
    """``/schema/command/<kind>``: each command class's defaults (``conf/command/*.yaml`` compose theirs in)."""
    from ..command import COMMANDS

    for kind, cls in COMMANDS.items():
        register(f"command/{kind}", class_defaults(cls))


def register(name: str, tree: Mapping[str, Any]) -> None:
    """Store ``tree`` as ``/schema/<name>`` (what a YAML's ``- /schema/<name>@_here_`` composes in)."""
    group, _, leaf = f"{GROUP}/{name}".rpartition("/")
    ConfigStore.instance().store(group=group, name=leaf, node=dict(tree))
