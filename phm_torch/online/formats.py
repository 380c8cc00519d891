"""Deployment formats of the online pipeline: TorchScript, torch.export (``.pt2``), AOTInductor packages.

Every writer writes atomically (:func:`~phm_torch.io.atomic.atomic_open`) one file that loads in a process that
never imports phm_torch, with the pipeline's metadata (provenance, tracking ranges, damage) inside it as the extra
file ``phm_metadata.json`` (:func:`~phm_torch.online.export.read_metadata` reads it for every format). The
non-TorchScript formats add ``format`` and ``pipeline`` (the constants phm-predict needs besides the program:
lengths, dtype, nominal vector and record, interval level, the output and reason names) to it.

* ``torchscript`` (``.pt``): the scripted :class:`~phm_torch.online.pipeline.OnlinePipeline`, its methods
  included (``torch.jit.load``); TorchScript is deprecated from torch 2.9 on, but it is the design card's format.
* ``export`` (``.pt2``): two :class:`torch.export.ExportedProgram` of :class:`~phm_torch.online.step.OnlineStep`,
  dynamic batch: ``model`` for full records (B, n_full) (what ``torch.export.load`` returns) and ``samples`` for
  selected samples (B, n_points) (``torch.export.pt2_archive._package.load_pt2(path).exported_programs``).
* ``aoti`` (``.aoti.pt2``): the same two programs compiled by AOTInductor into one package
  (``torch._inductor.package.load_package(path, model_name="model" | "samples")``), no Python needed to run it.
* ``onnx`` (``.onnx.zip``): the two programs as ONNX models run with ONNX Runtime, complete records only
  (:mod:`.onnx_format`; the optional extra ``phm-torch[onnx]``).
* ``executorch`` (``.pte.zip``): the two programs as methods of one ExecuTorch program, complete records, batches
  up to 256 per call (:mod:`.executorch_format`; the optional extra ``phm-torch[executorch]``).
"""

from __future__ import annotations

import copy
import json
import math
import os
import tempfile
import warnings
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any

import torch

from ..io.atomic import atomic_open
from .aoti_lowering import FDI_INDUCTOR_OPTIONS, STEP_INDUCTOR_OPTIONS, for_inductor
from .export import FDI_PROGRAM, METADATA_FILE, export_torchscript
from .extras import EXTRAS, require
from .input_contract import PIPELINE_CHECKS
from .output_diffs import max_difference
from .pipeline import OnlinePipeline
from .step import STEP_OUTPUTS, OnlineStep

DTYPES = {"float32": torch.float32, "float64": torch.float64}  # what a file may compute in (phm-export dtype=)
PROGRAMS = {"model": True, "samples": False}  # program name -> full records (else selected samples)
EXAMPLE_BATCH = 4  # tracing batch: any size > 1 (a batch of 1 would be specialised), dynamic from 1 up
MAX_BATCH = 1 << 20


def _finite_list(t: torch.Tensor) -> list[float] | None:
    return [float(v) for v in t.flatten().tolist()] if bool(torch.isfinite(t).all()) else None


def in_dtype(pipeline: OnlinePipeline, dtype: str | None) -> OnlinePipeline:
    """``pipeline`` computing in ``dtype`` (a name of ``DTYPES``; None: as it is), a copy where it changes.

    Why float64: the verdict score's slope is about 100 per unit of k near the health boundary, so float32 runtimes
    that sum the FDI's products in other orders (ONNX Runtime, ExecuTorch's portable kernels) give scores and RUL
    crossings 1e-4 apart, the float32 floor; in float64 every format agrees with eager float64 within 1e-7.
    ``ValueError`` naming ``dtype`` for another name, or for float32 asked of a float64 pipeline (its numbers
    would change: not a rewrite)."""
    wanted, own = check_dtype(dtype), pipeline.times.dtype
    if wanted is None or wanted == own:
        return pipeline
    if wanted.itemsize < own.itemsize:
        raise ValueError(f"dtype: {dtype!r} would round a {str(own).removeprefix('torch.')} pipeline; not written")
    return copy.deepcopy(pipeline).to(wanted).eval()


def check_dtype(dtype: str | None) -> torch.dtype | None:
    """The torch dtype of ``dtype`` (a name of ``DTYPES``, or None); ``ValueError`` naming ``dtype`` otherwise."""
    if dtype is None:
        return None
    if not isinstance(dtype, str) or dtype not in DTYPES:
        raise ValueError(f"dtype: must be one of {', '.join(DTYPES)} or null (the pipeline's own), got {dtype!r}")
    return DTYPES[dtype]


def pipeline_constants(pipeline: OnlinePipeline) -> dict[str, Any]:
    """What phm-predict reads of a pipeline besides its outputs, JSON-able (float32 values round-trip exactly)."""
    noise = float(pipeline.calibration_noise)
    return {
        "dtype": str(pipeline.times.dtype).removeprefix("torch."),
        "n_full": pipeline.n_full,
        "n_points": pipeline.n_points,
        "indices": [int(i) for i in pipeline.gappy.indices.tolist()],
        "sample_rate": pipeline.sample_rate,
        "horizon_hours": float(pipeline.times[-1]),
        "interval_level": pipeline.interval_level,
        "calibration_noise": None if math.isnan(noise) else noise,
        "calibrated": bool(torch.isfinite(pipeline.verdict_scale)),
        "nominal": _finite_list(pipeline.nominal),
        "interval_mask": _finite_list(pipeline.interval_mask),
        "interval_noise": _finite_list(pipeline.interval_noise),
        "nominal_record": _finite_list(pipeline.nominal_record),
        "inputs": ["x (B, n) current [A], NaN = missing", "offset (n,) [A] subtracted first (zeros: none)"],
        "outputs": list(STEP_OUTPUTS),
        "reasons": list(PIPELINE_CHECKS),
        "programs": dict(PROGRAMS),
    }


def export_programs(
    pipeline: OnlinePipeline, complete_only: bool = False, max_batch: int = MAX_BATCH
) -> dict[str, torch.export.ExportedProgram]:
    """The two :class:`OnlineStep` programs (full records, selected samples) of ``pipeline``, batch dynamic from 1
    to ``max_batch``; ``complete_only``: without the missing-sample path (see :class:`OnlineStep`)."""
    pipeline = pipeline.eval()
    dtype = pipeline.times.dtype
    batch = torch.export.Dim("batch", min=1, max=max_batch)
    out = {}
    for name, full in PROGRAMS.items():
        step = OnlineStep(pipeline, full, complete_only)
        n = step.length
        # in-distribution example records: the mean signal (a NaN would only be data, not a traced branch)
        x = pipeline.gappy.mean_hat.new_zeros(EXAMPLE_BATCH, n, dtype=dtype) + (
            pipeline.nominal_record
            if full and bool(torch.isfinite(pipeline.nominal_record).all())
            else torch.ones(n, dtype=dtype)
        )
        with torch.no_grad():
            out[name] = torch.export.export(
                step, (x, torch.zeros(n, dtype=dtype)), dynamic_shapes={"x": {0: batch}, "offset": None}, strict=False
            )
    return out


def _metadata(
    pipeline: OnlinePipeline,
    metadata: Mapping[str, Any] | None,
    fmt: str,
    limits: str | None = None,
    max_batch: int | None = None,
    programs: Sequence[str] = (),
) -> str:
    """The file's metadata; ``limits``: what the format cannot serve (then ``pipeline.missing_samples`` is false:
    records with a missing sample are refused by the loader); ``max_batch``: records per program call (the loader
    splits larger batches), None: no bound; ``programs``: the file's programs besides the two steps."""
    const = pipeline_constants(pipeline)
    const = {
        **const,
        "programs": {**const["programs"], **{name: False for name in programs}},
        "missing_samples": limits is None,
        "limits": limits,
        "max_batch": max_batch,
    }
    return json.dumps({**dict(metadata or {}), "format": fmt, "pipeline": const}, sort_keys=True)


def write_export(
    pipeline: OnlinePipeline,
    path: str | os.PathLike,
    metadata: Mapping[str, Any] | None = None,
    programs: dict[str, torch.export.ExportedProgram] | None = None,
) -> None:
    """Write the ``export`` format (a ``.pt2`` archive of :func:`export_programs`) atomically to ``path``."""
    from torch.export.pt2_archive._package import package_pt2  # what torch.export.save writes, several programs

    programs = programs or export_programs(pipeline)
    with atomic_open(path, "wb") as fh, warnings.catch_warnings():
        # buffers sharing storage (e.g. the verdict classifier that is the health classifier) are stored once
        warnings.filterwarnings("ignore", message="No complete tensor found in the group")
        package_pt2(
            fh, exported_programs=programs, extra_files={METADATA_FILE: _metadata(pipeline, metadata, "export")}
        )


class _SampleFDI(torch.nn.Module):
    """Complete selected samples (B, n_points) [A] in the pipeline's dtype -> k_hat (B, 8): the folded FDI of
    :meth:`OnlinePipeline.k_hat_of_samples` (its samples cast to the gappy layer's dtype first, as there)."""

    def __init__(self, pipeline: OnlinePipeline):
        super().__init__()
        self.folded = pipeline.folded_fdi
        self.dtype = pipeline.gappy.modes_hat.dtype

    def forward(self, samples: torch.Tensor) -> torch.Tensor:
        return self.folded(samples.to(self.dtype))


def fdi_program(pipeline: OnlinePipeline, max_batch: int = MAX_BATCH) -> torch.export.ExportedProgram | None:
    """The FDI alone, complete selected samples (B, n_points) [A] -> k_hat (B, 8), batch dynamic (None where the
    pipeline's FDI is not folded: a Bayesian gappy layer)."""
    if not pipeline.eval().fdi_folded:
        return None
    x = pipeline.gappy.mean_hat.detach().to(pipeline.times.dtype).expand(EXAMPLE_BATCH, -1).contiguous()
    batch = torch.export.Dim("batch", min=1, max=max_batch)
    with torch.no_grad():
        return torch.export.export(_SampleFDI(pipeline), (x,), dynamic_shapes={"samples": {0: batch}}, strict=False)


def write_aoti(
    pipeline: OnlinePipeline,
    path: str | os.PathLike,
    metadata: Mapping[str, Any] | None = None,
    programs: dict[str, torch.export.ExportedProgram] | None = None,
) -> None:
    """Compile :func:`export_programs` (and :func:`fdi_program` as ``fdi``) with AOTInductor (a C++ compiler is
    needed), each program rewritten by :func:`for_inductor`, and write the package atomically to ``path``; minutes
    on a small CPU."""
    from torch.export.pt2_archive._package import package_pt2

    programs = dict(programs or export_programs(pipeline))
    fdi = fdi_program(pipeline)
    if fdi is not None:
        programs[FDI_PROGRAM] = fdi
    files = {}
    with tempfile.TemporaryDirectory() as tmp:
        for name, ep in programs.items():
            options = {
                "aot_inductor.package": True,
                "aot_inductor.model_name_for_generated_files": name,
                "aot_inductor.output_path": str(Path(tmp) / name),
                **STEP_INDUCTOR_OPTIONS,
                **(FDI_INDUCTOR_OPTIONS if name == FDI_PROGRAM else {}),
            }
            files[name] = torch._inductor.aot_compile(for_inductor(ep.module()), ep.example_inputs[0], options=options)
        with atomic_open(path, "wb") as fh:
            meta = _metadata(pipeline, metadata, "aoti", programs=[n for n in programs if n not in PROGRAMS])
            package_pt2(fh, aoti_files=files, extra_files={METADATA_FILE: meta})


def _write_torchscript(
    pipeline: OnlinePipeline, path: str | os.PathLike, metadata: Mapping[str, Any] | None = None, programs: Any = None
) -> None:
    export_torchscript(pipeline, path, metadata)


def write_onnx(
    pipeline: OnlinePipeline, path: str | os.PathLike, metadata: Mapping[str, Any] | None = None, programs: Any = None
) -> None:
    """Write the ``onnx`` format (:mod:`.onnx_format`: complete records only) atomically to ``path``."""
    from . import onnx_format

    onnx_format.write_onnx(
        export_programs(pipeline, complete_only=True), path, _metadata(pipeline, metadata, "onnx", onnx_format.LIMITS)
    )


def write_executorch(
    pipeline: OnlinePipeline, path: str | os.PathLike, metadata: Mapping[str, Any] | None = None, programs: Any = None
) -> None:
    """Write the ``executorch`` format (:mod:`.executorch_format`: complete records, batches up to its
    ``MAX_BATCH``) atomically to ``path``."""
    from . import executorch_format as et

    et.write_executorch(
        export_programs(pipeline, complete_only=True, max_batch=et.MAX_BATCH),
        path,
        _metadata(pipeline, metadata, "executorch", et.LIMITS, et.MAX_BATCH),
    )


# format name -> (file suffix, writer(pipeline, path, metadata, programs))
WRITERS: dict[str, tuple[str, Callable[..., None]]] = {
    "torchscript": (".pt", _write_torchscript),
    "export": (".pt2", write_export),
    "aoti": (".aoti.pt2", write_aoti),
    "onnx": (".onnx.zip", write_onnx),
    "executorch": (".pte.zip", write_executorch),
}


def check_formats(formats: str | Sequence[str]) -> list[str]:
    """The format names, each known (``ValueError`` naming ``format`` and the value otherwise), duplicates dropped."""
    names = [formats] if isinstance(formats, str) else list(formats)
    if not names or not all(isinstance(n, str) for n in names):
        raise ValueError(f"format must be one of {sorted(WRITERS)} or a list of them, got {formats!r}")
    for n in names:
        if n not in WRITERS:
            raise ValueError(f"format: unknown format {n!r}; known: {', '.join(WRITERS)}")
    for n in names:  # an optional extra: refused before any work when it is not installed
        if n in EXTRAS:
            require(n)
    return list(dict.fromkeys(names))


def format_path(out: str | os.PathLike, fmt: str) -> Path:
    """The file of format ``fmt`` beside ``out``: its name without a known suffix, plus the format's suffix."""
    out = Path(out)
    name = out.name
    for suffix, _ in sorted(WRITERS.values(), key=lambda w: -len(w[0])):
        if name.endswith(suffix):
            name = name[: -len(suffix)]
            break
    return out.with_name(name + WRITERS[fmt][0])


def write_formats(
    pipeline: OnlinePipeline,
    out: str | os.PathLike,
    formats: str | Sequence[str],
    metadata: Mapping[str, Any] | None = None,
) -> dict[str, Path]:
    """Write ``pipeline`` in each of ``formats`` beside ``out`` (:func:`format_path`); returns format -> path."""
    names = check_formats(formats)
    programs = export_programs(pipeline) if set(names) & {"export", "aoti"} else None
    paths = {}
    for name in names:
        paths[name] = format_path(out, name)
        WRITERS[name][1](pipeline, paths[name], metadata, programs)
    return paths


def write_checked(
    pipeline: OnlinePipeline,
    out: str | os.PathLike,
    formats: str | Sequence[str],
    metadata: Mapping[str, Any] | None,
    probe: torch.Tensor,
) -> dict[str, Any]:
    """:func:`write_formats`, then each file reloaded as phm-predict reads it
    (:func:`~phm_torch.online.loaded.load_pipeline`) and its five outputs on ``probe`` (B, n_full) [A] compared
    with eager (a format that serves complete records only: on the probe's complete ones). Returns
    ``{"files": {format: path}, "max_abs_diff": {format: largest |reloaded - eager|}}`` (NaN where both are NaN
    counts as equal; a NaN on one side only is an infinite difference)."""
    from .loaded import load_pipeline

    paths = write_formats(pipeline, out, formats, metadata)
    diffs = {}
    probe = probe.to(pipeline.times.dtype)
    complete = torch.isfinite(probe.index_select(1, pipeline.gappy.indices.to(probe.device))).all(1)
    with torch.no_grad():
        eager = pipeline(probe)
        for name, path in paths.items():
            loaded = load_pipeline(path, name)
            # a format that serves complete records only (onnx, executorch) refuses the others: compared on the rest
            rows = slice(None) if getattr(loaded, "missing_samples", True) else complete
            diffs[name] = max(max_difference(a, b[rows]) for a, b in zip(loaded(probe[rows]), eager))
    return {"files": {k: str(v) for k, v in paths.items()}, "max_abs_diff": diffs}
