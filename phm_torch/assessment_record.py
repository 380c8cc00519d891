"""Which assessment function an artefact's labels came from, and whether two artefacts agree on it.

phi_a labels the training vectors of the health classifier and the inspections of a life split. A pipeline and a
life split labelled by different phi_a disagree near the health boundary, exactly where a run to failure crosses
it (the pretrained pipeline's hand-tuned sweep against the derived one: its health classifier said "faulty" an
inspection late for 25 of 40 histories). The stores record their assessment config; the bundle and the exported
pipeline carry it on (``assessment`` in their metadata), and phm-track compares it with a life split's.
"""

from __future__ import annotations

import json
from collections.abc import Mapping
from typing import Any

from .assessment.margins import NO_RESPONSE_DB

# settings that change how phi_a runs, not what it answers. group_size is one only within the settling tolerance:
# with max_extensions 0 it moves a few labels nearest the requirements (docs/dataset.md, "Settling and refinement")
RUN_ONLY = ("compile", "group_size")
# sweep settings a config may leave out, and what that means (SineSweep's code defaults): a store made before the
# shipped config set settling records none of them, and labels as one that records them at these values
# no_response_db (2026-11-29): a store labelled before it read every sweep reading; its records are read as labelled
# with the floor, which changes no label of 512 of the reference's importance-sampled vectors, 3 of 384 of the rudder's
# and 7 of 384 of a ball screw whose sweep sticks in dry friction (measured): re-generate such a store's labels
SWEEP_DEFAULTS = {
    "tolerance": 0.005,
    "max_extensions": 0,
    "refine": 0,
    "rotor_positions": 1,
    "no_response_db": NO_RESPONSE_DB,
}


def labelling(assessment: Mapping[str, Any] | None) -> dict[str, Any] | None:
    """The assessment config without its run-only settings (``RUN_ONLY``, at any depth) and with the sweep's
    ``SWEEP_DEFAULTS`` filled in where it leaves them out; None for None."""
    if assessment is None:
        return None

    def strip(node: Any) -> Any:
        if isinstance(node, Mapping):
            return {k: strip(v) for k, v in node.items() if k not in RUN_ONLY}
        if isinstance(node, (list, tuple)):
            return [strip(v) for v in node]
        return node

    out = strip(assessment)
    if isinstance(out.get("sweep"), dict):
        out["sweep"] = {**SWEEP_DEFAULTS, **out["sweep"]}
    return out


def same_labels(a: Mapping[str, Any] | None, b: Mapping[str, Any] | None) -> bool | None:
    """Whether two assessment configs label alike (None: one of them is unknown)."""
    if a is None or b is None:
        return None
    return json.dumps(labelling(a), sort_keys=True) == json.dumps(labelling(b), sort_keys=True)
