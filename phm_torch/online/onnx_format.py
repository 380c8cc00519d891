"""The ``onnx`` deployment format: the two :class:`~phm_torch.online.step.OnlineStep` programs as ONNX models,
run with ONNX Runtime (the optional extra ``pip install 'phm-torch[onnx]'``: onnx, onnxscript, onnxruntime).

The file (``.onnx.zip``) is a zip archive of two standard ONNX models, ``online/model.onnx`` (full records
(B, n_full)) and ``online/samples.onnx`` (selected samples (B, n_points)), dynamic batch, inputs ``x`` and
``offset`` and outputs named as ``STEP_OUTPUTS``, plus ``online/extra/phm_metadata.json`` (what
:func:`~phm_torch.online.export.read_metadata` reads; each model also carries it in its ``metadata_props``).
Unzipped, each model runs in any ONNX runtime without Python.

What ONNX cannot express: the masked least squares of a record with missing samples needs a Cholesky solve,
which ONNX (opset 18) has no operator for. The programs are therefore exported with
``OnlineStep(complete_only=True)``: they serve records whose selected samples are all present, the metadata's
``pipeline.missing_samples`` is false, and the loader refuses a record with a missing sample
(:class:`~phm_torch.online.loaded.UnservedRecord`). ``torch.searchsorted`` (the noise-level interpolation of the
OOD threshold and the intervals) has no ONNX translation either: it is decomposed into a comparison count, which
is exact for the sorted 1-D level tables it reads.
"""

from __future__ import annotations

import logging
import os
import tempfile
import zipfile
from collections.abc import Callable
from pathlib import Path

import torch

from ..io.atomic import atomic_open
from .export import METADATA_FILE
from .extras import require, without_searchsorted
from .step import STEP_OUTPUTS

ARCHIVE_DIR = "online"
LIMITS = (
    "complete records only: ONNX has no linear solve (Cholesky) for the masked least squares of a record "
    "with missing samples"
)


def onnx_bytes(program: torch.export.ExportedProgram, metadata: str) -> bytes:
    """One exported :class:`OnlineStep` program (complete_only) as a serialised ONNX model, batch dynamic."""
    require("onnx")
    program = without_searchsorted(program)
    batch = torch.export.Dim("batch", min=1, max=1 << 20)
    quiet = logging.getLogger("onnx_ir")  # one INFO line per deduplicated constant, hundreds per program
    level = quiet.level
    quiet.setLevel(logging.ERROR)
    try:
        onnx_program = torch.onnx.export(
            program,
            dynamic_shapes={"x": {0: batch}, "offset": None},
            dynamo=True,
            input_names=["x", "offset"],
            output_names=list(STEP_OUTPUTS),
            verbose=False,
            # the exporter's own graph optimiser left Clip nodes reading bound constants it had removed, on the
            # paper-scale step (ONNX Runtime: "Node input 'div_11_min_1' is not a graph input"); ONNX Runtime
            # optimises the graph itself when it loads it
            optimize=False,
        )
    finally:
        quiet.setLevel(level)
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "step.onnx"
        onnx_program.save(str(path), external_data=False)
        import onnx

        model = onnx.load(str(path))
    # unoptimised, the exporter leaves the graph's outputs under their node names: name them as STEP_OUTPUTS
    for out, name in zip(model.graph.output, STEP_OUTPUTS):
        if out.name != name:
            model.graph.node.append(onnx.helper.make_node("Identity", [out.name], [name]))
            out.name = name
    entry = model.metadata_props.add()
    entry.key, entry.value = METADATA_FILE, metadata
    return model.SerializeToString()


def write_onnx(programs: dict[str, torch.export.ExportedProgram], path: str | os.PathLike, metadata: str) -> None:
    """Write the ``onnx`` archive of ``programs`` (name -> complete-only program) atomically to ``path``."""
    models = {name: onnx_bytes(program, metadata) for name, program in programs.items()}
    with atomic_open(path, "wb") as fh, zipfile.ZipFile(fh, "w", zipfile.ZIP_DEFLATED) as archive:
        for name, data in models.items():
            archive.writestr(f"{ARCHIVE_DIR}/{name}.onnx", data)
        archive.writestr(f"{ARCHIVE_DIR}/extra/{METADATA_FILE}", metadata)


class OnnxProgram:
    """One ONNX model of the archive in an ONNX Runtime session: ``(x, offset) -> STEP_OUTPUTS`` as tensors,
    with as many intra-op threads as torch uses (so that benchmarks compare like with like)."""

    def __init__(self, data: bytes):
        import onnxruntime as ort

        options = ort.SessionOptions()
        options.intra_op_num_threads = torch.get_num_threads()
        options.inter_op_num_threads = 1
        self.session = ort.InferenceSession(data, options, providers=["CPUExecutionProvider"])

    def __call__(self, x: torch.Tensor, offset: torch.Tensor) -> tuple[torch.Tensor, ...]:
        out = self.session.run(list(STEP_OUTPUTS), {"x": x.numpy(), "offset": offset.numpy()})
        return tuple(torch.from_numpy(o) for o in out)


def load_onnx(path: str | os.PathLike, names: tuple[str, ...] = ("model", "samples")) -> dict[str, Callable]:
    """The programs ``names`` of an ``onnx`` archive, each an :class:`OnnxProgram`."""
    require("onnx", write=False)
    with zipfile.ZipFile(path) as archive:
        data = {name: archive.read(f"{ARCHIVE_DIR}/{name}.onnx") for name in names}
    return {name: OnnxProgram(blob) for name, blob in data.items()}
