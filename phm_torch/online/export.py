"""TorchScript export of the online pipeline."""

from __future__ import annotations

import json
import os
import zipfile
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import torch

from ..io.atomic import atomic_open
from .pipeline import OnlinePipeline

METADATA_FILE = "phm_metadata.json"  # the extra file of the archive with the pipeline's provenance
FDI_PROGRAM = "fdi"  # an aoti package's FDI alone: complete selected samples (B, n_points) -> k_hat (B, 8)
# rul_calibration.json's entries an exported pipeline's metadata carries, whichever app exports it (phm-evaluate
# or phm-export): the input contract's thresholds and the fault rate P(faulty) was calibrated at (phm-track's
# verdict evidence)
CALIBRATION_METADATA = (
    "tracking_nrmse",
    "tracking_nrmse_healthy",
    "shape_correlation_min",
    "unexplained_ratio_max",
    "verdict_prior_faulty",
    "spike_step_max",
    "timing_ratio_max",
    "held_out_quality",  # the verdict's and the RUL's figures on held-out records (phm-predict's caveats)
)


def calibration_metadata(calibration: Mapping[str, Any]) -> dict[str, Any]:
    """The :data:`CALIBRATION_METADATA` entries of a calibration record (rul_calibration.json's content) that
    are set."""
    return {key: calibration[key] for key in CALIBRATION_METADATA if calibration.get(key) is not None}


def export_torchscript(
    pipeline: OnlinePipeline, path: str | os.PathLike, metadata: Mapping[str, Any] | None = None
) -> torch.jit.ScriptModule:
    """Script ``pipeline`` (eval mode) and write it atomically to ``path``; returns the scripted module.

    ``metadata`` (JSON-able: the actuator and command the pipeline belongs to, under ``provenance``; the input
    contract's ``tracking_nrmse``; the damage config, under ``damage``, which phm-track takes as its process
    model) is stored as the archive's extra file ``phm_metadata.json``. The file loads with ``torch.jit.load`` in a
    process that never imports phm_torch; :func:`read_metadata` reads the extra file back.
    """
    pipeline = pipeline.eval()
    scripted = torch.jit.script(pipeline)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    extra = {METADATA_FILE: json.dumps(dict(metadata or {}), sort_keys=True)}
    with atomic_open(path, "wb") as fh:
        torch.jit.save(scripted, fh, _extra_files=extra)
    return scripted


def read_metadata(path: str | os.PathLike) -> dict[str, Any]:
    """The ``phm_metadata.json`` of an exported pipeline (``{}`` for a file exported before it existed)."""
    try:  # the archive is a zip file: read the entry without loading (or running) the program
        with zipfile.ZipFile(path) as archive:
            names = [n for n in archive.namelist() if n.endswith(f"/extra/{METADATA_FILE}")]
            if not names:
                return {}
            data = json.loads(archive.read(names[0]))
    except (OSError, zipfile.BadZipFile, json.JSONDecodeError) as e:
        raise ValueError(f"{path}: not a readable exported pipeline ({type(e).__name__}: {e})") from None
    if not isinstance(data, dict):
        raise ValueError(f"{path}: {METADATA_FILE} must hold a JSON object, got {type(data).__name__}")
    return data
