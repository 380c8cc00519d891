"""Files that travel beside an exported pipeline for the tracker: its FDI response (:mod:`.response`) and its
near-nominal FDI (:mod:`.near_nominal`). One rule for both: ``auto`` reads ``<pipeline stem><suffix>`` beside the
pipeline where there is one, ``null`` none, anything else is a path that must exist; each then checks that it
belongs to the pipeline."""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any

from .near_nominal import NearNominalFDI
from .response import FDIResponse

log = logging.getLogger(__name__)

SUFFIXES = {"response": ".fdi_response.json", "near_nominal": ".near_nominal.pt"}
LOADERS = {"response": FDIResponse.load, "near_nominal": NearNominalFDI.load}


def companion(kind: str, setting: Any, pipeline_path: Path, model: Any) -> FDIResponse | NearNominalFDI | None:
    """The ``kind`` (``response`` or ``near_nominal``) file the setting names for the pipeline at ``pipeline_path``,
    loaded and checked against ``model`` (ValueError naming the setting for a missing or foreign file)."""
    if kind not in SUFFIXES:
        raise ValueError(f"companion: unknown kind {kind!r} (one of {sorted(SUFFIXES)})")
    if setting is None:
        return None
    auto = str(setting) == "auto"
    path = pipeline_path.with_name(pipeline_path.stem + SUFFIXES[kind]) if auto else Path(str(setting))
    if not path.is_file():
        if auto:
            return None
        raise ValueError(f"{kind}: no such file {str(path)!r} (auto: the one beside the pipeline; null: none)")
    log.info("%s%s: %s", kind, " beside the pipeline" if auto else "", path)
    loaded = LOADERS[kind](path)
    loaded.check_for(model, str(pipeline_path))
    return loaded
