"""How phm-run composes its stages' configs: each stage is an app's own config (conf/<app>.yaml) composed with
the overrides phm-run passes it (the run's actuator, command and damage law, chosen once for the whole run; a data
experiment's dataset and assessment settings; the stage's own list in conf/run.yaml)."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from hydra import compose, initialize_config_dir
from hydra.core.global_hydra import GlobalHydra
from omegaconf import DictConfig

from .. import provenance
from ..params import CONF_DIR
from . import common


def compose_stage(app: str, overrides: list[str]) -> DictConfig:
    """The composed config of ``app`` (conf/<app>.yaml) with ``overrides``, inside or outside a Hydra app.

    The config-group choices of the shared groups (``actuator``, ``command``) are kept under ``choices``
    (what :func:`common.choice` reads), since a composed config outside ``@hydra.main`` has no runtime."""
    if GlobalHydra.instance().is_initialized():
        cfg = compose(config_name=app, overrides=overrides, return_hydra_config=True)
    else:
        with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
            cfg = compose(config_name=app, overrides=overrides, return_hydra_config=True)
    return common.keep_choices(cfg, (*SHARED_GROUPS, DAMAGE_GROUP))


DATA_KEYS = ("dataset", "assessment")  # config nodes of phm-generate that a run-level experiment may set


def _dotted(prefix: str, node: Any) -> list[str]:
    """Hydra overrides ``a.b.c=value`` for every leaf of a config node (lists stay whole values)."""
    if isinstance(node, DictConfig):
        return [o for key, value in node.items() for o in _dotted(f"{prefix}.{key}", value)]
    return [f"{prefix}={json.dumps(common.plain(node))}"]


SHARED_GROUPS = ("actuator", "command")  # chosen once for the run and passed to every stage
DAMAGE_GROUP = "damage"  # the damage law, chosen once for the run and passed to the stages that read one


def shared_overrides(cfg: DictConfig) -> list[str]:
    """The run's actuator and command for every stage: ``actuator=<name>`` and ``command=<name>`` (the
    choice), then their values as dotted overrides (so ``phm-run actuator.gear_ratio=150`` reaches every
    stage too), and the run's config search path (a user's own config folder)."""
    out = []
    for key in SHARED_GROUPS:
        name = common.choice(cfg, key)
        if name is None:
            record = common.requested_provenance(cfg)[key]
            name = provenance.known_name(key, record["sha256"]) if record else None
        if name is None:
            raise ValueError(
                f"{key}: phm-run needs a {key} config chosen by name ({key}=<name> of a "
                f"conf/{key}/<name>.yaml in the config search path)"
            )
        out += [f"{key}={name}", *_dotted(key, cfg[key])]
    searchpath = _searchpath()
    if searchpath:
        out.append(f"hydra.searchpath={json.dumps(searchpath)}")
    return out


def damage_overrides(cfg: DictConfig) -> list[str]:
    """The run's damage law for the stages that read one: ``damage=<name>`` when chosen by name, then its values as
    dotted overrides (``phm-run damage.rate_scale_sigma=0.2`` reaches each stage); no ``damage`` node: nothing."""
    if cfg.get(DAMAGE_GROUP) is None:
        return []
    name = common.choice(cfg, DAMAGE_GROUP)
    return [*([f"{DAMAGE_GROUP}={name}"] if name else []), *_dotted(DAMAGE_GROUP, cfg[DAMAGE_GROUP])]


def _searchpath() -> list[str]:
    from hydra.core.hydra_config import HydraConfig

    return list(HydraConfig.get().searchpath) if HydraConfig.initialized() else []


def generate_overrides(cfg: DictConfig) -> list[str]:
    """phm-generate's overrides in a run: the run's ``generate`` list, then the dataset/assessment settings
    that a data experiment (``phm-run experiment=paper``) or the command line (``phm-run
    +assessment.sweep.refine=1``) put at the run level, which win. Those are passed as ``++key=value``: a
    setting whose code default the YAML does not restate is added, one it lists is overridden."""
    return [
        *stage_overrides(cfg.generate, "generate"),
        *(f"++{o}" for key in DATA_KEYS if key in cfg for o in _dotted(key, cfg[key])),
    ]


STAGE_LISTS = ("cases", "generate", "train", "evaluate", "track", "workbench")  # phm-run's per-stage override lists


def dropped_defaults(cfg: DictConfig) -> dict[str, list[str]]:
    """Per stage, the entries of conf/run.yaml's default list whose setting the run's list no longer makes: a list
    given on the command line (``'generate=["dataset.n_train=300"]'``) replaces the whole default list (chunk size,
    compiled simulator, ...), which a run-level setting (``+dataset.n_train=300``) would have kept."""
    shipped = compose_stage("run", [])
    out: dict[str, list[str]] = {}
    for stage in STAGE_LISTS:
        given = common.plain(cfg.get(stage)) or []
        default = common.plain(shipped.get(stage)) or []
        if not isinstance(given, list) or not isinstance(default, list):
            continue
        keys = {str(item).partition("=")[0].lstrip("+~") for item in given}
        lost = [str(item) for item in default if str(item).partition("=")[0].lstrip("+~") not in keys]
        if lost:
            out[stage] = lost
    return out


def stage_overrides(value: Any, name: str) -> list[str]:
    items = common.plain(value) or []
    if not isinstance(items, list) or not all(isinstance(v, str) for v in items):
        raise ValueError(f"{name} must be a list of Hydra overrides (strings), got {items!r}")
    out = []
    for item in items:  # a shipped example file is found from any working directory
        key, _, path = item.partition("=")
        if key.lstrip("+~").split(".")[0] in (*SHARED_GROUPS, DAMAGE_GROUP):
            raise ValueError(
                f"{name}: {item!r} sets the actuator, command or damage law of one stage only; set it for the "
                f"whole run (phm-run {item.lstrip('+~')})"
            )
        shipped = CONF_DIR.parent / path
        if key == "measurements" and path and not Path(path).exists() and shipped.is_file():
            item = f"{key}={shipped}"
        out.append(item)
    return out
