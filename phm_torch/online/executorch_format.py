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


def sum_by_product(
    x: torch.Tensor, dim: list[int] | None = None, keepdim: bool = False, *, dtype: torch.dtype | None = None
) -> torch.Tensor:
    """``aten.sum.dim_IntList`` as a product with a vector of ones, in float64: ExecuTorch's portable sum kernel
    accumulates a float64 tensor in float32 (measured 1.3e-7 relative; the polynomial classifier's score and the RUL
    crossing carried it to 9e-6), its matrix product in float64. Exact for bool and integer counts below 2^53."""
    out = dtype or (x.dtype if x.is_floating_point() else torch.int64)
    dims = sorted({d % x.dim() for d in dim}) if dim else list(range(x.dim()))
    kept = [d for d in range(x.dim()) if d not in dims]
    n = 1
    for d in dims:
        n *= x.shape[d]
    y = x.permute(*kept, *dims).to(torch.float64).reshape(*[x.shape[d] for d in kept], n)
    y = (y @ torch.ones(n, 1, dtype=torch.float64, device=x.device)).squeeze(-1)  # a matrix product: mv sums in float32
    if keepdim:
        for d in dims:
            y = y.unsqueeze(d)
    return y.to(out)


def norm_by_product(
    x: torch.Tensor,
    ord: float = 2.0,
    dim: list[int] | None = None,
    keepdim: bool = False,
    *,
    dtype: torch.dtype | None = None,
) -> torch.Tensor:
    """``aten.linalg_vector_norm`` with its sum as :func:`sum_by_product` (the portable kernel accumulates float64
    in float32 as its sum does)."""
    a = x.abs().to(dtype or x.dtype)
    if ord == float("inf"):
        return a.amax(dim if dim else None, keepdim)
    if ord == float("-inf"):
        return a.amin(dim if dim else None, keepdim)
    if ord == 0:
        return sum_by_product((a != 0).to(a.dtype), dim, keepdim)
    return sum_by_product(a.pow(ord), dim, keepdim).pow(1.0 / ord)


# float64 programs: the reductions whose portable kernels accumulate in float32, as float64 products
FLOAT64_SUMS = {
    torch.ops.aten.sum.dim_IntList: sum_by_product,
    torch.ops.aten.linalg_vector_norm.default: norm_by_product,
}


def pte_bytes(programs: dict[str, torch.export.ExportedProgram]) -> bytes:
    """The ExecuTorch program (one method per entry of ``programs``, complete-only :class:`OnlineStep`); a float64
    program's sums and norms become products (``FLOAT64_SUMS``)."""
    require("executorch")
    from executorch.exir import to_edge_transform_and_lower

    lowered = {}
    for name, program in programs.items():
        program = without_searchsorted(program)
        if program.example_inputs[0][0].dtype == torch.float64:
            program = program.run_decompositions(FLOAT64_SUMS)
        lowered[name] = program
    edge = to_edge_transform_and_lower(lowered)
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
