"""What the formats served by optional runtimes (ONNX Runtime, ExecuTorch) share: the check that their extra is
installed, and the rewrite of the one operator of the complete-record step that neither runtime has."""

from __future__ import annotations

import importlib.util

import torch

# format -> (modules needed to write (and reload-check) it, modules needed to run it, the pip install to run)
EXTRAS = {
    "onnx": (
        ("onnx", "onnxscript", "onnxruntime"),
        ("onnxruntime",),
        "pip install 'phm-torch[onnx]'  (or: pip install onnx onnxscript onnxruntime)",
    ),
    "executorch": (
        ("executorch",),
        ("executorch",),
        "pip install 'phm-torch[executorch]'  (or: pip install executorch)",
    ),
}


def require(fmt: str, write: bool = True) -> None:
    """``ValueError`` naming the format and the pip install to run when a module of its extra is missing."""
    modules = EXTRAS[fmt][0 if write else 1]
    missing = [m for m in modules if importlib.util.find_spec(m) is None]
    if missing:
        raise ValueError(
            f"format: {fmt!r} needs the optional packages {', '.join(missing)}, not installed; run: {EXTRAS[fmt][2]}"
        )


def searchsorted_by_count(
    sorted_sequence: torch.Tensor,
    values: torch.Tensor,
    *,
    out_int32: bool = False,
    right: bool = False,
    side: str | None = None,
    sorter: torch.Tensor | None = None,
) -> torch.Tensor:
    """``torch.searchsorted`` of a sorted 1-D sequence as the count of its entries below each value (neither ONNX
    nor ExecuTorch's portable kernels have searchsorted): a decomposition of ``aten.searchsorted.Tensor``, exact for
    the sorted noise-level tables the step interpolates in."""
    if sorted_sequence.dim() != 1 or sorter is not None:
        raise ValueError(
            f"searchsorted rewrite: a sorted 1-D sequence without sorter only, got a "
            f"{sorted_sequence.dim()}-D sequence{' with a sorter' if sorter is not None else ''}"
        )
    v = values.unsqueeze(-1)
    below = (sorted_sequence <= v) if (right or side == "right") else (sorted_sequence < v)
    return below.sum(-1).to(torch.int32 if out_int32 else torch.int64)


def without_searchsorted(program: torch.export.ExportedProgram) -> torch.export.ExportedProgram:
    """``program`` with ``aten.searchsorted`` decomposed by :func:`searchsorted_by_count`."""
    return program.run_decompositions({torch.ops.aten.searchsorted.Tensor: searchsorted_by_count})
