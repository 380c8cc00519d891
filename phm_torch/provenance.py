"""Provenance: which actuator and which test command an artefact belongs to.

Every artefact (dataset store, surrogate bundle, exported pipeline, ``rul_calibration.json``, workbench
report, fitted LF shapes) records an *actuator record* and a *command record*:

* actuator: ``{"name", "sha256", "values"}``: the config name, the SHA-256 of its canonical JSON values
  (so a renamed copy is recognised and an edited one is not), and the values themselves (an app that
  consumes the artefact without ``actuator=`` adopts them);
* command: ``{"name", "sha256", "params"}``: the config name, the hash and the command's parameters
  (``_target_`` included).

:func:`reconcile` is the one check every consuming app runs: an explicit choice that differs from the
artefact's is an error naming both; without an explicit choice the artefact's record is adopted and the
app says so.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import logging
from collections.abc import Mapping
from typing import Any

from .params import ActuatorParams

log = logging.getLogger(__name__)

KEYS = ("actuator", "command")


def _canonical(value: Any) -> Any:
    """JSON-able copy with floats normalised (1 and 1.0 hash alike; tuples become lists)."""
    if isinstance(value, Mapping):
        return {str(k): _canonical(v) for k, v in sorted(value.items(), key=lambda kv: str(kv[0]))}
    if isinstance(value, (list, tuple)):
        return [_canonical(v) for v in value]
    if isinstance(value, bool) or value is None or isinstance(value, str):
        return value
    if isinstance(value, (int, float)):
        return float(value)
    raise ValueError(f"provenance: cannot record a value of type {type(value).__name__}: {value!r}")


def digest(values: Mapping[str, Any]) -> str:
    """SHA-256 (hex) of the canonical JSON of ``values``."""
    text = json.dumps(_canonical(values), sort_keys=True, separators=(",", ":"))
    return hashlib.sha256(text.encode()).hexdigest()


def actuator_values(params: ActuatorParams) -> dict[str, Any]:
    """The actuator's values as a plain mapping (the YAML's fields, ``lf_shape`` as a mapping).

    Optional fields at their defaults are left out, so that a field added to the datasheet later (with a
    default that keeps the physics) does not change the hash of every actuator recorded before it."""
    values = dataclasses.asdict(params)
    values["nominal_faults"] = list(params.nominal_faults)
    for f in dataclasses.fields(params):
        if f.default is not dataclasses.MISSING:
            default = f.default
        elif f.default_factory is not dataclasses.MISSING:
            default = f.default_factory()
        else:
            continue
        if getattr(params, f.name) == default:
            values.pop(f.name)
    return _canonical(values)


def actuator_record(name: str, params: ActuatorParams) -> dict[str, Any]:
    """``{"name", "sha256", "values"}`` of the actuator ``params`` chosen as config ``name``."""
    values = actuator_values(params)
    return {"name": str(name), "sha256": digest(values), "values": values}


def command_record(name: str, node: Mapping[str, Any]) -> dict[str, Any]:
    """``{"name", "sha256", "params"}`` of the test command config ``node`` (its ``_target_`` included)."""
    if not isinstance(node, Mapping):
        raise ValueError(f"command: expected a mapping of command parameters, got {node!r}")
    params = _canonical(dict(node))
    return {"name": str(name), "sha256": digest(params), "params": params}


def describe(record: Mapping[str, Any] | None) -> str:
    """One line: ``name (sha256 1f2e3d4c)`` or ``unknown``."""
    if not record:
        return "unknown"
    return f"{record.get('name', '?')} (sha256 {str(record.get('sha256', ''))[:8]})"


def validate(record: Any, key: str, where: str) -> dict[str, Any]:
    """Check that ``record`` is a well-formed actuator or command record and that its hash matches its values."""
    field = "values" if key == "actuator" else "params"
    if (
        not isinstance(record, Mapping)
        or not isinstance(record.get(field), Mapping)
        or not isinstance(record.get("name"), str)
        or not isinstance(record.get("sha256"), str)
    ):
        raise ValueError(f"{where}: {key} provenance must be {{name, sha256, {field}}}, got {record!r}")
    if digest(record[field]) != record["sha256"]:
        raise ValueError(
            f"{where}: {key} provenance {describe(record)} does not match its own {field} (edited by hand?)"
        )
    return dict(record)


def reconcile(
    recorded: Mapping[str, Any] | None, requested: Mapping[str, Any] | None, explicit: bool, key: str, where: str
) -> dict[str, Any] | None:
    """The record an app must use, given what an artefact ``recorded`` and what the app's config ``requested``.

    Args:
        recorded: the artefact's record (``None``: an artefact written before provenance existed).
        requested: the app's own record (from its config), or ``None``.
        explicit: whether the user chose ``requested`` (``actuator=...``) rather than the app defaulting it.
        key: ``"actuator"`` or ``"command"``.  where: the artefact, for messages (e.g. its path).

    Returns:
        the record to use: the artefact's when it has one (adopted, with a log line, when nothing explicit
        was asked), else ``requested``.

    Raises:
        ValueError: an explicit choice whose hash differs from the artefact's (one line naming both).
    """
    if recorded is None:
        if requested is not None:
            log.warning(
                "%s records no %s (written before provenance existed): assuming %s", where, key, describe(requested)
            )
        return None if requested is None else dict(requested)
    recorded = validate(recorded, key, where)
    if requested is None:
        log.info("%s: using the %s the artefact was made for, %s", where, key, describe(recorded))
        return recorded
    if requested["sha256"] == recorded["sha256"]:
        return recorded
    if explicit:
        raise ValueError(
            f"{key}={requested['name']} ({describe(requested)}) differs from the {key} {where} "
            f"was made for: {describe(recorded)}"
        )
    log.warning(
        "%s was made for %s %s; adopting it instead of the default %s",
        where,
        key,
        describe(recorded),
        describe(requested),
    )
    print(f"note: {where} was made for {key} {describe(recorded)}; using it (pass {key}=... to choose)", flush=True)
    return recorded


def require_same(recorded: Mapping[str, Any] | None, used: Mapping[str, Any], where: str) -> None:
    """Check that an artefact ``where`` (its ``recorded`` records, ``None`` for none) belongs to the actuator and
    command ``used`` (records, a key ``None`` where nothing is known): :func:`reconcile` with every known
    record treated as explicit, so a difference is a ValueError naming both."""
    recorded = recorded or {}
    for key in KEYS:
        reconcile(recorded.get(key), used.get(key), used.get(key) is not None, key, where)


def known_name(key: str, sha256: str) -> str | None:
    """The shipped config (``conf/<key>/<name>.yaml``) whose values hash to ``sha256``, or ``None``."""
    from omegaconf import OmegaConf

    from .command import with_defaults
    from .params import CONF_DIR

    for path in sorted((CONF_DIR / key).glob("*.yaml")):
        data = OmegaConf.to_container(OmegaConf.load(path), resolve=True)
        if not isinstance(data, dict):
            continue
        try:  # a command file as composed: its class's defaults filled in
            record = (
                actuator_record(path.stem, ActuatorParams.from_mapping(data))
                if key == "actuator"
                else command_record(path.stem, with_defaults(data))
            )
        except (ValueError, TypeError):
            continue
        if record["sha256"] == sha256:
            return path.stem
    return None


def from_config(config: Mapping[str, Any], names: Mapping[str, str | None] | None = None) -> dict[str, Any]:
    """``{"actuator", "command"}`` records of a resolved config holding ``actuator`` and ``command`` nodes
    (e.g. the config a store was generated with); a node that is absent gives ``None``. Names come from
    ``names``, else from the shipped config with the same values, else ``"custom"``."""
    names = names or {}
    out: dict[str, Any] = {}
    for key in KEYS:
        node = config.get(key)
        if node is None:
            out[key] = None
            continue
        record = (
            actuator_record("custom", ActuatorParams.from_mapping(node))
            if key == "actuator"
            else command_record("custom", node)
        )
        record["name"] = names.get(key) or known_name(key, record["sha256"]) or "custom"
        out[key] = record
    return out
