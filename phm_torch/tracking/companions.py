"""Files that travel beside an exported pipeline for the tracker: its FDI response (:mod:`.response`), its
near-nominal FDI (:mod:`.near_nominal`) and the tracker's figures on simulated histories of its actuator
(:mod:`.tracker_check`). One rule for all three: ``auto`` reads ``<pipeline stem><suffix>`` beside the
pipeline where there is one, ``null`` none, anything else is a path that must exist; each then checks that it
belongs to the pipeline."""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any

from .near_nominal import NearNominalFDI
from .response import FDIResponse
from .tracker_check import TrackerCheck

log = logging.getLogger(__name__)

SUFFIXES = {
    "response": ".fdi_response.json",
    "near_nominal": ".near_nominal.pt",
    "tracker_check": ".tracker_check.json",
}
LOADERS = {"response": FDIResponse.load, "near_nominal": NearNominalFDI.load, "tracker_check": TrackerCheck.load}
MAKERS = {  # how a user makes each for their own pipeline (docs/prognostics.md, "Life tracking")
    "response": "phm-track index=<a life split's index.csv> truth=<its truth.json> response_out=<path>",
    "near_nominal": "python scripts/fit_near_nominal.py --pipeline <pipeline> --life <life split> --store <store>",
    "tracker_check": "phm-run stages=[companions] (the tracker on simulated histories of the pipeline's actuator)",
}


def missing_message(kind: str, pipeline_path: Path) -> str:
    """What ``auto`` not finding the ``kind`` file beside the pipeline means, and how to make one: a pipeline made by
    phm-run has neither, and near nominal the tracker then reads the pipeline's own k_hat."""
    name = pipeline_path.stem + SUFFIXES[kind]
    return (
        f"{kind}=auto: no {name} beside {pipeline_path}; near nominal the tracker reads the pipeline's k_hat as it is "
        f"(the pretrained one reads small damages at 0.55-0.8 of their growth; docs/prognostics.md). Make one with: "
        f"{MAKERS[kind]}"
    )


def companion(
    kind: str, setting: Any, pipeline_path: Path, model: Any
) -> FDIResponse | NearNominalFDI | TrackerCheck | None:
    """The ``kind`` (``response``, ``near_nominal`` or ``tracker_check``) file the setting names for the pipeline at ``pipeline_path``,
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
