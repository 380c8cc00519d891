"""The ``executorch`` deployment format: the two :class:`~phm_torch.online.step.OnlineStep` programs as one
ExecuTorch program (``.pte``, methods ``model`` and ``samples``), run with ExecuTorch's runtime: the edge path for
an on-board computer (the optional extra ``pip install 'phm-torch[executorch]'``).

The file (``.pte.zip``) is a zip archive of ``online/program.pte`` and ``online/extra/phm_metadata.json`` (what
:func:`~phm_torch.online.export.read_metadata` reads; a flatbuffer program has no room for it). Unzipped, the
``.pte`` runs in ExecuTorch's C++ runtime (``Module("program.pte").execute("model", {x, offset})``) with the
portable kernels, no delegate.

Limits, recorded in the metadata (``pipeline.missing_samples`` false, ``pipeline.limits``, ``pipeline.max_batch``):

* complete records only, as ONNX: the masked least squares of a record with missing samples does not lower
  (``to_executorch`` fails on the program with the missing-sample path: executorch 1.5.1, torch 2.13), so the
  programs are ``OnlineStep(complete_only=True)``, and ``torch.searchsorted`` is rewritten
  (:func:`~phm_torch.online.extras.searchsorted_by_count`);
* the batch has an upper bound (``MAX_BATCH``): ExecuTorch plans every intermediate's memory ahead of time for the
  largest batch; the loader splits a larger batch into chunks.
"""

from __future__ import annotations

import os
import zipfile
from collections.abc import Callable

import torch

from ..io.atomic import atomic_open
from .export import METADATA_FILE
from .extras import require, without_searchsorted

MAX_BATCH = 256  # records per call; the memory plan grows with it (one record is the on-board case)
ARCHIVE_DIR = "online"
LIMITS = "complete records only: the masked least squares of a record with missing samples does not lower to ExecuTorch"


def pte_bytes(programs: dict[str, torch.export.ExportedProgram]) -> bytes:
    """The ExecuTorch program (one method per entry of ``programs``, complete-only :class:`OnlineStep`)."""
    require("executorch")
    from executorch.exir import to_edge_transform_and_lower

    edge = to_edge_transform_and_lower({name: without_searchsorted(p) for name, p in programs.items()})
    return edge.to_executorch().buffer


def write_executorch(programs: dict[str, torch.export.ExportedProgram], path: str | os.PathLike, metadata: str) -> None:
    """Write the ``executorch`` archive of ``programs`` atomically to ``path``."""
    data = pte_bytes(programs)
    with atomic_open(path, "wb") as fh, zipfile.ZipFile(fh, "w", zipfile.ZIP_DEFLATED) as archive:
        archive.writestr(f"{ARCHIVE_DIR}/program.pte", data)
        archive.writestr(f"{ARCHIVE_DIR}/extra/{METADATA_FILE}", metadata)


class ExecuTorchMethod:
    """One method of a loaded ExecuTorch program: ``(x, offset) -> STEP_OUTPUTS`` as tensors."""

    def __init__(self, program: object, name: str):
        self.program, self.method = program, program.load_method(name)

    def __call__(self, x: torch.Tensor, offset: torch.Tensor) -> tuple[torch.Tensor, ...]:
        return tuple(self.method.execute([x, offset]))


def load_executorch(path: str | os.PathLike, names: tuple[str, ...] = ("model", "samples")) -> dict[str, Callable]:
    """The methods ``names`` of an ``executorch`` archive, each an :class:`ExecuTorchMethod`."""
    require("executorch", write=False)
    from executorch.runtime import Runtime

    with zipfile.ZipFile(path) as archive:
        program = Runtime.get().load_program(archive.read(f"{ARCHIVE_DIR}/program.pte"))
    return {name: ExecuTorchMethod(program, name) for name in names}
