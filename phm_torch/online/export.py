"""TorchScript export of the online pipeline."""

from __future__ import annotations

import os
from pathlib import Path

import torch

from ..io.atomic import atomic_open
from .pipeline import OnlinePipeline


def export_torchscript(pipeline: OnlinePipeline, path: str | os.PathLike) -> torch.jit.ScriptModule:
    """Script ``pipeline`` (eval mode) and write it atomically to ``path``; returns the scripted module.

    The file loads with ``torch.jit.load`` in a process that never imports phm_torch.
    """
    pipeline = pipeline.eval()
    scripted = torch.jit.script(pipeline)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_open(path, "wb") as fh:
        torch.jit.save(scripted, fh)
    return scripted
