"""What a store records about itself: the fingerprint of the data-defining config, the repository revision, and
the manifest's metadata (:func:`store_records`)."""

from __future__ import annotations

import copy
import hashlib
import json
import subprocess
from collections.abc import Mapping
from typing import Any

import torch

from ... import __version__
from ...assessment import MARGIN_NAMES, AssessmentFunction
from ...data import generation as gen
from ...params import CONF_DIR
from .settings import GenerateSettings

# Config nodes that determine the data (the fingerprint); the rest only says where and how to run.
DATA_NODES = ("actuator", "command", "dataset", "assessment", "seed")
# dataset.life is not in it: a life split is added to a finished store without invalidating it; the life
# data record their own settings (truth.json) and resume per actuator on their own key.
NOT_FINGERPRINTED = ("life",)


def fingerprint(config: Mapping[str, Any]) -> tuple[str, dict[str, Any]]:
    """SHA-256 of the data-defining nodes of ``config`` (plain data; canonical JSON) and those nodes."""
    data = {key: copy.deepcopy(config.get(key)) for key in DATA_NODES}
    if isinstance(data["dataset"], dict):
        data["dataset"] = {k: v for k, v in data["dataset"].items() if k not in NOT_FINGERPRINTED}
    data["package_version"] = __version__
    text = json.dumps(data, sort_keys=True, separators=(",", ":"))
    return hashlib.sha256(text.encode()).hexdigest(), data


def git_revision() -> str:
    """The repository's HEAD commit (with ``-dirty`` if modified), or ``unknown``."""
    root = CONF_DIR.parent
    try:
        rev = subprocess.run(
            ["git", "rev-parse", "HEAD"], cwd=root, capture_output=True, text=True, timeout=10, check=True
        ).stdout.strip()
        dirty = subprocess.run(
            ["git", "status", "--porcelain", "--untracked-files=no"],
            cwd=root,
            capture_output=True,
            text=True,
            timeout=10,
            check=True,
        ).stdout.strip()
    except (OSError, subprocess.SubprocessError):
        return "unknown"
    return rev + ("-dirty" if dirty else "")


def store_records(
    settings: GenerateSettings,
    assessment: AssessmentFunction,
    plan: gen.Plan,
    label_plan: gen.Plan | None,
    fp: str,
    sampling: Mapping[str, Any],
) -> tuple[dict[str, Any], dict[str, Any]]:
    """The merged store's ``metadata`` (the whole config, seeds, provenance, versions, the sampling and the
    assessment sweep) and the ``extra`` entries of its manifest (chunking, seed, provenance, version)."""
    seeds = {"seed": settings.seed, **plan.seeds, **(label_plan.seeds if label_plan is not None else {})}
    metadata = {
        "config": copy.deepcopy(dict(settings.config)),
        "fingerprint": fp,
        "seeds": seeds,
        "provenance": settings.provenance,
        "package_version": __version__,
        "git_revision": git_revision(),
        "torch_version": torch.__version__,
        "margin_names": list(MARGIN_NAMES),
        "sampling": sampling,
        "assessment_sweep": assessment.record(),
    }
    extra = {
        "seed": settings.seed,
        "provenance": settings.provenance,
        "package_version": __version__,
        "chunk_size": plan.chunk_size,
        "n_chunks": plan.n_chunks,
        "sampling": sampling,
        "assessment_sweep": assessment.record(),
    }
    if label_plan is not None:
        extra |= {"label_chunk_size": label_plan.chunk_size, "n_label_chunks": label_plan.n_chunks}
    return metadata, extra
