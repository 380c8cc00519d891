"""An exported online pipeline loaded from any format, behind one interface (what phm-predict diagnoses with).

:func:`load_pipeline` reads a file written by :mod:`phm_torch.online.formats` and returns a
:class:`LoadedPipeline`: :meth:`~LoadedPipeline.run` gives every output of the online step for a batch of records
(:class:`StepResult`), :meth:`~LoadedPipeline.pipeline_reasons` which of the pipeline's checks fired, and the
attributes the input contract reads (``dtype``, ``n_full``, ``sample_rate``, ``nominal``, ``nominal_record``, ...).
A TorchScript file answers through its scripted methods (as phm-predict always has, older files included), an
``export``, ``aoti``, ``onnx`` or ``executorch`` file through one call of its
:class:`~phm_torch.online.step.OnlineStep` program (the last two: complete records only, :class:`UnservedRecord`
otherwise). The format
is the one the file's metadata names, else its suffix; a ``format`` given that the file is not of is an error.
"""

from __future__ import annotations

import abc
import inspect
import math
import os
import warnings
import zipfile
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch

from .export import FDI_PROGRAM, read_metadata
from .input_contract import pipeline_reasons
from .step import STEP_OUTPUTS

FORMATS = ("torchscript", "export", "aoti", "onnx", "executorch")
CALL_BATCH = 256  # most records per program call (see ProgramPipeline)


class UnservedRecord(ValueError):
    """A record the loaded file's format cannot serve (e.g. one with a missing sample for an ``onnx`` file)."""


@dataclass(frozen=True)
class StepResult:
    """Outputs of the online step for B records: k_hat (B, 8); k_lower, k_upper (B, 8) or None (a pipeline
    without intervals); score (B,) (> 0 healthy); p_faulty (B,) (NaN uncalibrated); rul (B, 3) [h]; ood (B,) bool;
    residual (B,) [A]; noise (B,) relative noise as measured (NaN unknown); current (B, n) [A] as the pipeline saw
    it (after the bench baseline)."""

    k_hat: torch.Tensor
    k_lower: torch.Tensor | None
    k_upper: torch.Tensor | None
    score: torch.Tensor
    p_faulty: torch.Tensor
    rul: torch.Tensor
    ood: torch.Tensor
    residual: torch.Tensor
    noise: torch.Tensor
    current: torch.Tensor


class LoadedPipeline(abc.ABC):
    """Common interface of a loaded pipeline (see the module docstring); ``format`` names its file format."""

    format = ""
    metadata: dict[str, Any]
    dtype: torch.dtype
    n_full: int
    sample_rate: float
    horizon_hours: float  # the RUL horizon [h]: a bound at it means "beyond" (inf where a file lacks it)

    @abc.abstractmethod
    def run(self, x: torch.Tensor, bench_nominal: torch.Tensor | None = None) -> StepResult:
        """Every output for records x (B, n_full) or (B, n_points) [A] as measured; ``bench_nominal`` (n_full,) [A]:
        the measuring bench's healthy record, whose difference from the training model is removed first."""

    @abc.abstractmethod
    def pipeline_reasons(self, x: torch.Tensor) -> list[list[str]] | None:
        """Which pipeline checks fire for records x as the pipeline sees them (see :func:`.pipeline_reasons`)."""

    def __call__(self, x: torch.Tensor) -> tuple[torch.Tensor, ...]:
        """The pipeline's own five outputs (k_hat, score, rul, ood, residual) of records x, as ``forward``."""
        r = self.run(x)
        return r.k_hat, r.score, r.rul, r.ood, r.residual

    @property
    def calibrated(self) -> bool:
        """Whether P(faulty) can be calibrated (a TorchScript file older than the verdict calibration cannot)."""
        return True

    @property
    def can_rebase(self) -> bool:
        """Whether the pipeline carries its training model's nominal record (so a bench baseline applies)."""
        nominal = getattr(self, "nominal_record", None)
        return nominal is not None and bool(torch.isfinite(nominal).all())


class TorchScriptPipeline(LoadedPipeline):
    """A scripted (or eager) :class:`~phm_torch.online.OnlinePipeline`; other attributes pass through to it."""

    format = "torchscript"

    def __init__(self, module: Any, metadata: dict[str, Any] | None = None):
        self.module, self.metadata = module, dict(metadata or {})
        self.dtype = module.times.dtype
        self.horizon_hours = float(module.times[-1])
        self.noise_reusable = _noise_reusable(module)

    def __getattr__(self, name: str) -> Any:
        if name == "module":  # not set yet (unpickling, copy): no recursion
            raise AttributeError(name)
        return getattr(self.module, name)

    @property
    def calibrated(self) -> bool:
        return hasattr(self.module, "faulty_probability")

    @property
    def can_rebase(self) -> bool:
        return hasattr(self.module, "rebase") and super().can_rebase

    def run(self, x: torch.Tensor, bench_nominal: torch.Tensor | None = None) -> StepResult:
        m = self.module
        x = x.to(self.dtype)
        nan = torch.full((x.shape[0],), float("nan"), dtype=self.dtype)
        noise_known = hasattr(m, "noise_level") and x.shape[1] == int(m.n_full)
        with torch.no_grad():
            noise = m.noise_level(x) if noise_known else nan  # as measured, before the baseline
            current = m.rebase(x, bench_nominal) if bench_nominal is not None else x
            # forward would estimate the same noise again (9 % of a batched step); after a baseline it must read
            # the rebased record's own
            reuse = noise_known and bench_nominal is None and self.noise_reusable
            k_hat, score, rul, ood, residual = m(current, noise) if reuse else m(current)
            p_faulty = m.faulty_probability(score) if self.calibrated else nan
            lower = upper = None
            if hasattr(m, "k_interval"):  # widths follow the noise where the file's (or eager) method takes it
                method = m.k_interval
                schema = method.schema if hasattr(method, "schema") else inspect.signature(method)
                lower, upper = (
                    m.k_interval(k_hat, noise.to(k_hat.dtype))
                    if noise_known and "noise" in str(schema)
                    else m.k_interval(k_hat)
                )
        return StepResult(k_hat, lower, upper, score, p_faulty, rul, ood, residual, noise, current)

    def pipeline_reasons(self, x: torch.Tensor) -> list[list[str]] | None:
        return pipeline_reasons(self.module, x)


def _noise_reusable(module: Any) -> bool:
    """Whether ``module(x)`` estimates the noise of full records exactly as ``module.noise_level(x)`` does, so that
    the level measured for the report can be passed in: every pipeline since both read the first samples
    (``_estimated_noise``); a file whose ``noise_level`` read the whole record (the original pretrained one) is
    left to estimate its own."""
    code = getattr(getattr(module, "noise_level", None), "code", None)
    if code is None:  # an eager pipeline: this code's noise_level
        return hasattr(module, "_estimated_noise")
    return "_estimated_noise" in code


def _tensor(values: list[float] | None, dtype: torch.dtype) -> torch.Tensor | None:
    return None if values is None else torch.tensor(values, dtype=dtype)


class ProgramPipeline(LoadedPipeline):
    """An ``export`` (``.pt2``) or ``aoti`` file: its two :class:`~.step.OnlineStep` programs, ``model`` for full
    records and ``samples`` for selected samples, and the constants of its metadata's ``pipeline``."""

    def __init__(self, programs: dict[str, Any], metadata: dict[str, Any], fmt: str, path: str, fdi: Any = None):
        const = metadata.get("pipeline")
        if not isinstance(const, dict) or set(const.get("outputs", [])) != set(STEP_OUTPUTS):
            raise ValueError(
                f"pipeline: {path!r} has no online-step metadata of this phm_torch version "
                f"(re-export it with phm-export)"
            )
        self.programs, self.metadata, self.format = programs, metadata, fmt
        self.dtype = getattr(torch, const["dtype"])
        self.n_full, self.n_points = int(const["n_full"]), int(const["n_points"])
        self.sample_rate, self.interval_level = float(const["sample_rate"]), float(const["interval_level"])
        self.horizon_hours = float(const.get("horizon_hours") or math.inf)  # files before it: never censored
        noise = const["calibration_noise"]
        self.calibration_noise = torch.tensor(math.nan if noise is None else noise, dtype=self.dtype)
        for name in ("nominal", "interval_mask", "interval_noise", "nominal_record"):
            setattr(self, name, _tensor(const[name], self.dtype))
        self.reason_names = list(const["reasons"])
        self.indices = torch.tensor(const["indices"], dtype=torch.long)  # the selected samples of a full record
        self.missing_samples = bool(const.get("missing_samples", True))  # False: complete records only
        self.limits = const.get("limits")
        self.max_batch = const.get("max_batch")  # records per program call (None: any)
        # records per call: a larger batch is split, so that a call's intermediates stay in cache (the pretrained
        # pipeline's aoti step: 9,200 records/s in one call of 4,096, 13,000 in calls of 256)
        self.call_batch = min(int(self.max_batch or CALL_BATCH), CALL_BATCH)
        self.fdi_program = fdi  # the FDI alone (aoti packages from this version on), else None
        self._zeros: dict[int, torch.Tensor] = {}

    def _outputs(self, x: torch.Tensor, offset: torch.Tensor | None) -> dict[str, torch.Tensor]:
        n = x.shape[1]
        if n not in (self.n_full, self.n_points) or x.dim() != 2:
            raise ValueError(
                f"records: expected (B, {self.n_full}) full records or (B, {self.n_points}) selected "
                f"samples, got {tuple(x.shape)}"
            )
        program = self.programs["model" if n == self.n_full else "samples"]
        if not self.missing_samples:
            samples = x.index_select(1, self.indices) if n == self.n_full else x
            gaps = (~torch.isfinite(samples)).sum(1)
            if bool(gaps.any()):
                i = int(gaps.nonzero()[0, 0])
                raise UnservedRecord(
                    f"record {i} misses {int(gaps[i])} of its {self.n_points} selected samples "
                    f"(NaN); this {self.format!r} pipeline serves {self.limits}; use its "
                    f"torchscript, export or aoti file for such records"
                )
        if offset is None:  # zeros, made once per input length
            offset = self._zeros.get(n)
            if offset is None:
                offset = self._zeros[n] = torch.zeros(n, dtype=self.dtype)
        x, offset = x.to(self.dtype).contiguous(), offset.to(self.dtype).contiguous()
        with torch.no_grad():
            if x.shape[0] <= self.call_batch:
                out = program(x, offset)
            else:
                outs = [program(c.contiguous(), offset) for c in x.split(self.call_batch)]
                out = [torch.cat(parts) for parts in zip(*outs)]
        return dict(zip(STEP_OUTPUTS, out))

    def k_hat_of_samples(self, samples: torch.Tensor) -> torch.Tensor:
        """k_hat (B, 8) of complete selected samples (B, n_points) [A]: the file's FDI program alone (as the
        TorchScript pipeline's method); ``ValueError`` for a file without one."""
        if self.fdi_program is None:
            raise ValueError(f"pipeline: this {self.format!r} file has no FDI program (aoti packages have one)")
        if samples.dim() != 2 or samples.shape[1] != self.n_points:
            raise ValueError(f"samples: expected (B, {self.n_points}), got {tuple(samples.shape)}")
        if not bool(torch.isfinite(samples).all()):
            raise UnservedRecord("samples: the FDI program serves complete samples only (a NaN found)")
        with torch.no_grad():
            return self.fdi_program(samples.to(self.dtype).contiguous())

    def run(self, x: torch.Tensor, bench_nominal: torch.Tensor | None = None) -> StepResult:
        x = x.to(self.dtype)
        offset = None
        if bench_nominal is not None:  # as OnlinePipeline.rebase: x - (bench_nominal - nominal_record)
            if self.nominal_record is None or bench_nominal.shape != self.nominal_record.shape:
                raise ValueError("rebase: the pipeline has no nominal record of the record's length")
            offset = bench_nominal.to(self.dtype) - self.nominal_record
        o = self._outputs(x, offset)
        current = x if offset is None else x - offset
        return StepResult(
            o["k_hat"],
            o["k_lower"],
            o["k_upper"],
            o["score"],
            o["p_faulty"],
            o["rul"],
            o["ood"],
            o["residual"],
            o["noise"],
            current,
        )

    def pipeline_reasons(self, x: torch.Tensor) -> list[list[str]] | None:
        flags = self._outputs(x, None)["reasons"]
        return [[name for name, on in zip(self.reason_names, row.tolist()) if on] for row in flags]


class _FlatCall:
    """An AOTInductor program called with its tensors as a flat list (its C++ loader's ``boxed_run``): the package's
    Python wrapper rebuilds the call's input and output specs from JSON at every call, about 40 us of one
    record's 0.45 ms step. The programs here take only tensors and return a tensor or a tuple of them. A torch whose
    package has no such loader (a private attribute) is called through its wrapper."""

    def __init__(self, compiled: Any):
        from torch.utils import _pytree

        self.compiled, self.loader = compiled, getattr(compiled, "loader", None)
        if not hasattr(self.loader, "boxed_run"):
            self.loader = None
        else:
            self.single = _pytree.treespec_loads(self.loader.get_call_spec()[1]).is_leaf()

    def __call__(self, *tensors: torch.Tensor) -> Any:
        if self.loader is None:
            return self.compiled(*tensors)
        out = self.loader.boxed_run(list(tensors))
        return out[0] if self.single else tuple(out)


SUFFIXES = {
    ".aoti.pt2": "aoti",
    ".onnx.zip": "onnx",
    ".pte.zip": "executorch",
    ".pt2": "export",
    ".pt": "torchscript",
}  # longest first


def _format_of(path: Path, metadata: dict[str, Any]) -> str:
    """The file's format from its content (the metadata's ``format``; a TorchScript archive has ``code/``), which
    must be the one its suffix names (``ValueError`` naming the file otherwise)."""
    found = metadata.get("format")
    if found is None:
        with zipfile.ZipFile(path) as archive:  # read_metadata has checked it is one
            names = archive.namelist()
        found = "torchscript" if any("/code/" in n or n.endswith("constants.pkl") for n in names) else None
    by_name = next((fmt for suffix, fmt in SUFFIXES.items() if path.name.endswith(suffix)), None)
    if found is None:
        raise ValueError(
            f"pipeline: {str(path)!r} is no exported pipeline (no TorchScript code, no "
            f"phm_metadata.json naming its format)"
        )
    if by_name is not None and by_name != found:
        raise ValueError(
            f"pipeline: {str(path)!r} holds a {found!r} pipeline but its name ends as a {by_name!r} "
            f"file's ({', '.join(f'{k} {v}' for k, v in SUFFIXES.items())})"
        )
    return str(found)


def load_pipeline(path: str | os.PathLike, format: str | None = None) -> LoadedPipeline:
    """Load an exported pipeline of any format (see the module docstring); ``ValueError`` naming the field and
    value for an unknown format or a file not of the format asked for."""
    path = Path(path)
    if format is not None and format not in FORMATS:
        raise ValueError(f"format: unknown format {format!r}; known: {', '.join(FORMATS)}")
    if not path.is_file():
        raise ValueError(f"pipeline: no such file {str(path)!r} (export one with phm-evaluate or phm-export)")
    metadata = read_metadata(path)
    found = _format_of(path, metadata)
    if format is not None and found != format:
        raise ValueError(f"pipeline: {str(path)!r} is a {found!r} file, not format={format!r}")
    if found == "torchscript":
        try:
            with warnings.catch_warnings():  # the deprecation of TorchScript, chosen here on purpose
                warnings.filterwarnings(
                    "ignore", message=r".*torch\.jit\.load. is deprecated", category=DeprecationWarning
                )
                module = torch.jit.load(str(path))
        except RuntimeError as e:
            raise ValueError(f"pipeline: {str(path)!r} is not a TorchScript file ({str(e).splitlines()[0]})") from None
        return TorchScriptPipeline(module, metadata)
    try:
        if found == "export":
            from torch.export.pt2_archive._package import load_pt2

            programs = {name: ep.module() for name, ep in load_pt2(str(path)).exported_programs.items()}
        elif found == "aoti":
            from torch._inductor.package import load_package  # aoti_load_package, with the model's name

            names = (metadata.get("pipeline") or {}).get("programs") or ("model", "samples")
            programs = {name: _FlatCall(load_package(str(path), model_name=name)) for name in names}
        elif found == "onnx":
            from .onnx_format import load_onnx

            programs = load_onnx(path)
        elif found == "executorch":
            from .executorch_format import load_executorch

            programs = load_executorch(path)
        else:
            raise ValueError(f"pipeline: {str(path)!r} names the unknown format {found!r}")
    except (RuntimeError, KeyError, zipfile.BadZipFile) as e:
        raise ValueError(
            f"pipeline: {str(path)!r} is not a readable {found!r} file ({type(e).__name__}: "
            f"{str(e).splitlines()[0] if str(e) else ''})"
        ) from None
    fdi = programs.pop(FDI_PROGRAM, None)
    if set(programs) != {"model", "samples"}:
        raise ValueError(f"pipeline: {str(path)!r} holds the programs {sorted(programs)}, not model and samples")
    return ProgramPipeline(programs, metadata, found, str(path), fdi)


def as_loaded(model: Any) -> LoadedPipeline:
    """``model`` as a :class:`LoadedPipeline` (a scripted or eager ``OnlinePipeline`` is wrapped)."""
    return model if isinstance(model, LoadedPipeline) else TorchScriptPipeline(model)
