"""An eager :class:`~phm_torch.online.pipeline.OnlinePipeline` rebuilt from a TorchScript pipeline file.

A file written by ``phm-export`` (any version: the shipped pretrained one predates the consistency check, the
noise-scaled residual limit, the health stop, the unidentified components and the coarse event grid) holds the
scripted pipeline, and the surrogate bundle it was made from may be gone. :func:`pipeline_from_torchscript`
rebuilds the eager pipeline from the file alone, so that it can be written again in any format
(:func:`rewrite_pipeline`, ``phm-export pipeline=<file.pt>``):

* each submodule's class is found by its scripted ``original_name`` (:data:`CLASSES`), and the module is restored
  with the file's parameters, buffers and plain attributes (those the archive's ``code/`` files declare as
  ``name : type``; their values are read with ``getattr`` on the loaded module) and its submodules, recursively;
* the pipeline itself is built by its constructor with arguments inferred from the file (the damage model's grid,
  propagators and nominal vector as the file stores them), so that a part the file lacks gets exactly the value
  the constructor gives when its argument is None (no consistency check, the residual threshold at every noise,
  no health stop, nothing unidentified) and a buffer the file lacks is derived as the constructor derives it
  (e.g. ``coarse_index``); then every tensor of the file is loaded into it (an error if one has no place) and
  every plain attribute of the file set.

The file is read with ``torch.jit.load`` and its metadata as JSON (:func:`~phm_torch.online.export.read_metadata`):
nothing is unpickled.
"""

from __future__ import annotations

import argparse
import logging
import math
import os
import re
import warnings
import zipfile
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import torch
from torch import nn

from ..surrogates.classifiers.mlp import MLPClassifier
from ..surrogates.classifiers.polynomial_svm import PolynomialSVM
from ..surrogates.classifiers.rbf_svm import RBFSVM
from ..surrogates.fdi_ensemble import FDIEnsemble
from ..surrogates.fdi_mlp import FDIMLP
from ..surrogates.forward import ForwardSurrogate
from ..surrogates.full_signal_check import FullSignalCheck
from ..surrogates.gappy_pod import GappyPOD
from .consistency import ConsistencyCheck
from .export import read_metadata
from .fdi_interval import DEFAULT_LEVEL
from .output_diffs import output_diffs
from .pipeline import OnlinePipeline

log = logging.getLogger(__name__)

# scripted original_name -> the class rebuilt from the file's state (the pipeline's own parts are built by it)
CLASSES: dict[str, type[nn.Module]] = {
    cls.__name__: cls
    for cls in (
        GappyPOD,
        FDIEnsemble,
        FDIMLP,
        MLPClassifier,
        PolynomialSVM,
        RBFSVM,
        FullSignalCheck,
        ConsistencyCheck,
        ForwardSurrogate,
        nn.Linear,
        nn.ModuleList,
        nn.Sequential,
        nn.Tanh,
        nn.ReLU,
        nn.Identity,
    )
}
# the pipeline's submodules: restored from the file and passed to the constructor, or (residual_limit) built by it
PIPELINE_CHILDREN = ("gappy", "fdi", "classifier", "verdict_classifier", "full_check", "consistency_check")
BUILT_CHILDREN = ("residual_limit", "folded_fdi")  # derived by the constructor
BUILT_ATTRIBUTES = ("fdi_folded",)  # derived by the constructor from the parts: an older file's value is stale
# non-persistent buffers the constructor makes: verdict_stop_index (from health_stop_index), crossing_marker (zero)
BUILT_BUFFERS = ("verdict_stop_index", "crossing_marker")
MODULE_INTERNALS = ("training", "_is_full_backward_hook")  # declared by every scripted module, not its state
# largest |converted - file| / max(1, |file|) of any output rewrite_pipeline accepts: a float32 pipeline's rounding
# (records with missing samples: the gappy layer's Woodbury path now starts from its solve matrix, 1e-5 of k_hat)
TOLERANCE = 1e-4
_ANNOTATION = re.compile(r"^  (\w+) : ([^=]+?)(?: = .*)?$")


class _StoredDamage:
    """What the pipeline's constructor reads of a damage model (the RUL grid, its propagators, the nominal vector),
    as the file stores them."""

    def __init__(self, times: torch.Tensor, propagators: torch.Tensor, nominal: torch.Tensor, path: str):
        self.grid, self.propagators, self.nominal, self.path = times, propagators, nominal, path

    def transitions(self, t: torch.Tensor) -> tuple[torch.Tensor, None]:
        return self.propagators, None

    def __getattr__(self, name: str) -> Any:
        raise AttributeError(
            f"pipeline {self.path!r}: the file stores the damage model's grid, propagators and nominal vector only, "
            f"not its {name!r}"
        )


class _Archive:
    """The ``code/`` declarations of a TorchScript archive: the attribute names of each scripted class."""

    def __init__(self, path: Path):
        self.path = path
        with zipfile.ZipFile(path) as archive:
            names = archive.namelist()
            root = names[0].split("/", 1)[0] if names else ""
            self.sources = {
                n[len(root) + 1 :]: archive.read(n).decode()
                for n in names
                if n.startswith(f"{root}/code/") and n.endswith(".py")
            }
        if not self.sources:
            raise ValueError(f"pipeline: {str(path)!r} is no TorchScript archive (no code/ in it)")

    def attributes(self, module: torch.jit.ScriptModule) -> dict[str, str]:
        """``{name: type}`` the archive declares for ``module``'s class (``__torch__.a.b.C`` is class C of
        code/__torch__/a/b.py; a mangled ``__torch__.a.b.___torch_mangle_3.C`` that of .../b/___torch_mangle_3.py)."""
        qualified = module._c._type().qualified_name()
        *package, cls = qualified.split(".")
        source = self.sources.get("code/" + "/".join(package) + ".py", "")
        lines = source.splitlines()
        header = f"class {cls}(Module):"
        if header not in lines:
            raise ValueError(f"pipeline: {str(self.path)!r} declares no class {qualified} in its code/")
        out = {}
        for line in lines[lines.index(header) + 1 :]:
            if not line.startswith("  ") or line.startswith("  def "):
                break
            match = _ANNOTATION.match(line)
            if match:
                out[match[1]] = match[2].strip()
        return out


def _plain(module: torch.jit.ScriptModule, archive: _Archive) -> dict[str, Any]:
    """The module's plain attributes (neither tensors of its state nor submodules) and their values."""
    state = {n for n, _ in module.named_parameters(recurse=False)} | {n for n, _ in module.named_buffers(recurse=False)}
    children = {n for n, _ in module.named_children()}
    names = [n for n in archive.attributes(module) if n not in state | children and n not in MODULE_INTERNALS]
    values = {}
    for name in names:
        value = getattr(module, name)
        values[name] = value.detach().clone() if isinstance(value, torch.Tensor) else value
    return values


def _restore(module: torch.jit.ScriptModule, archive: _Archive, where: str) -> nn.Module:
    """The eager module of a scripted one: its class (:data:`CLASSES`) with the file's parameters, buffers, plain
    attributes and submodules (restored alike); no constructor runs (its arguments are not in the file)."""
    name = module.original_name
    cls = CLASSES.get(name)
    if cls is None:
        raise ValueError(
            f"pipeline: {str(archive.path)!r}: submodule {where!r} is a {name}, which this phm_torch cannot rebuild "
            f"(known: {', '.join(CLASSES)})"
        )
    out = cls.__new__(cls)
    nn.Module.__init__(out)
    for key, p in module.named_parameters(recurse=False):
        out.register_parameter(key, nn.Parameter(p.detach().clone(), requires_grad=p.requires_grad))
    for key, b in module.named_buffers(recurse=False):
        out.register_buffer(key, b.detach().clone())
    for key, value in _plain(module, archive).items():
        setattr(out, key, value)
    for key, child in module.named_children():
        out.add_module(key, _restore(child, archive, f"{where}.{key}" if where else key))
    return out.eval()


def _shares_storage(a: nn.Module, b: nn.Module) -> bool:
    """Whether the scripted modules a and b hold the same tensors (one module under two names when scripted)."""
    ta, tb = list(a.state_dict().values()), list(b.state_dict().values())
    return len(ta) == len(tb) > 0 and all(x.data_ptr() == y.data_ptr() for x, y in zip(ta, tb))


def _optional(value: torch.Tensor | None) -> float | None:
    return None if value is None or math.isnan(float(value)) else float(value)


def convert_scripted(module: torch.jit.ScriptModule, path: str | os.PathLike) -> tuple[OnlinePipeline, list[str]]:
    """The eager pipeline of a loaded TorchScript pipeline ``module`` (read from ``path``, whose archive declares
    its attributes) and the names of the state entries the file lacks, derived by the constructor."""
    path = Path(path)
    if getattr(module, "original_name", None) != "OnlinePipeline":
        raise ValueError(
            f"pipeline: {str(path)!r} holds a TorchScript {getattr(module, 'original_name', type(module).__name__)}, "
            f"not an online pipeline (OnlinePipeline, written by phm-export)"
        )
    archive = _Archive(path)
    children = dict(module.named_children())
    unknown = sorted(set(children) - set(PIPELINE_CHILDREN) - set(BUILT_CHILDREN))
    missing = [name for name in ("gappy", "fdi", "classifier") if name not in children]
    if unknown or missing:
        raise ValueError(
            f"pipeline: {str(path)!r}: the online pipeline's submodules {sorted(children)} lack {missing} or hold "
            f"{unknown}, which this phm_torch's OnlinePipeline has no place for"
        )
    parts = {name: _restore(children[name], archive, name) for name in PIPELINE_CHILDREN if name in children}
    attrs = _plain(module, archive)
    buf = dict(module.named_buffers(recurse=False))
    shared = "verdict_classifier" not in children or _shares_storage(
        children["classifier"], children["verdict_classifier"]
    )
    has_full = bool(attrs.get("has_full_check", parts.get("full_check", nn.Identity()).__class__ is not nn.Identity))
    has_consistency = bool(attrs.get("has_consistency", False))
    limit = children.get("residual_limit")
    n_points = int(parts["gappy"].modes_hat.shape[0])
    verdict = (float(buf["verdict_scale"]), float(buf["verdict_offset"])) if "verdict_scale" in buf else None
    lacking = [k for k in ("times", "propagators", "nominal", "deltas", "direction") if k not in buf]
    lacking += [k for k in ("n_full", "residual_threshold", "min_count") if k not in attrs]
    if lacking:
        raise ValueError(f"pipeline: {str(path)!r}: the online pipeline has no {', '.join(lacking)}")
    pipeline = OnlinePipeline(
        parts["gappy"],
        parts["fdi"],
        parts["classifier"],
        _StoredDamage(buf["times"], buf["propagators"], buf["nominal"], str(path)),
        buf["deltas"],
        buf["direction"],
        int(attrs["n_full"]),
        float(attrs["residual_threshold"]),
        min(1.0, int(attrs["min_count"]) / n_points),  # min_count itself is set from the file below
        full_check=parts["full_check"] if has_full else None,
        fdi_deltas=buf.get("fdi_deltas"),
        fdi_direction=buf.get("fdi_direction"),
        rate_scales=buf.get("rate_scales"),
        verdict=None if verdict is None or any(math.isnan(v) for v in verdict) else verdict,
        nominal_record=buf.get("nominal_record"),
        k_half_widths=buf.get("k_half_widths"),
        interval_level=float(attrs.get("interval_level", DEFAULT_LEVEL)),
        calibration_noise=_optional(buf.get("calibration_noise")),
        interval_noise=buf.get("interval_noise"),
        verdict_classifier=None if shared else parts["verdict_classifier"],
        consistency=parts["consistency_check"] if has_consistency else None,
        residual_limits=None if limit is None else (limit.values.tolist(), limit.levels.tolist()),
        fdi_health_stop=buf["health_stop_index"].tolist() if "health_stop_index" in buf else None,
        unidentified=[j for j in range(8) if float(buf["unknown_shift"][2, j]) != 0.0]
        if "unknown_shift" in buf
        else None,
        # the file's event-search grid (its RUL numbers), else the constructor's default
        **{key: attrs[key] for key in ("sample_rate", "coarse") if key in attrs},
    )
    # a scripted module lists its derived (non-persistent) buffers too: the constructor made them from the restored parts
    stored = {
        k: v
        for k, v in module.state_dict().items()
        if k.split(".")[0] not in BUILT_CHILDREN[1:] and k not in BUILT_BUFFERS
    }
    result = pipeline.load_state_dict(stored, strict=False)  # the file's tensors, every one (checked below)
    if result.unexpected_keys:
        raise ValueError(
            f"pipeline: {str(path)!r} holds {sorted(result.unexpected_keys)}, which this phm_torch's OnlinePipeline "
            f"has no place for"
        )
    for name, value in attrs.items():
        if name not in BUILT_ATTRIBUTES:
            setattr(pipeline, name, value)
    return pipeline.eval(), sorted(result.missing_keys)


def load_scripted(path: str | os.PathLike) -> torch.jit.ScriptModule:
    """``torch.jit.load`` of a TorchScript pipeline file (deprecation filtered: TorchScript is read on purpose);
    ``ValueError`` naming the file for anything else (a ``.pt2`` program, a pickle, a missing file)."""
    path = Path(path)
    if not path.is_file():
        raise ValueError(f"pipeline: no such file {str(path)!r}")
    try:
        fmt = read_metadata(path).get("format")
    except ValueError as e:  # no zip archive
        raise ValueError(f"pipeline: {e}") from None
    if fmt not in (None, "torchscript"):
        raise ValueError(f"pipeline: {str(path)!r} is an {fmt!r} file, not a TorchScript online pipeline")
    _Archive(path)  # TorchScript code in it (a torch.save pickle has none): never handed to an unpickler
    try:
        with warnings.catch_warnings():
            warnings.filterwarnings("ignore", message=r".*torch\.jit\.load. is deprecated", category=DeprecationWarning)
            return torch.jit.load(str(path), map_location="cpu")
    except RuntimeError as e:
        raise ValueError(f"pipeline: {str(path)!r} is not a TorchScript file ({str(e).splitlines()[0]})") from None


def pipeline_from_torchscript(path: str | os.PathLike) -> tuple[OnlinePipeline, dict[str, Any]]:
    """The eager :class:`OnlinePipeline` (eval mode) of the TorchScript pipeline file ``path`` and the file's
    metadata (``{}`` for a file written before it existed). ``ValueError`` naming the file for one that is not a
    TorchScript online pipeline."""
    module = load_scripted(path)
    pipeline, derived = convert_scripted(module, path)
    if derived:
        log.info("pipeline %s lacks %s: derived as the constructor does", path, ", ".join(derived))
    return pipeline, read_metadata(path)


def probe_records(pipeline: OnlinePipeline, seed: int = 0) -> torch.Tensor:
    """Full records (7, n_full) [A] to compare two forms of ``pipeline`` on: its nominal record (the selected
    samples of its mean signal elsewhere when it has none), four copies with 1 % white noise, one with 3 of its
    selected samples missing (NaN) and one of noise alone (out of distribution)."""
    dtype = pipeline.times.dtype
    base = pipeline.nominal_record.clone()
    if not bool(torch.isfinite(base).all()):
        mean = pipeline.gappy.mean_hat.to(dtype)
        base = torch.full((pipeline.n_full,), float(mean.mean()), dtype=dtype).index_copy(
            0, pipeline.gappy.indices, mean
        )
    g = torch.Generator().manual_seed(seed)
    scale = float(base.pow(2).mean().sqrt())
    noisy = base + 0.01 * scale * torch.randn(4, base.shape[0], generator=g, dtype=dtype)
    holed = base.clone()
    holed[pipeline.gappy.indices[[3, 100 % pipeline.n_points, pipeline.n_points - 2]]] = float("nan")
    foreign = scale * torch.randn(base.shape[0], generator=g, dtype=dtype)
    return torch.stack([base, *noisy, holed, foreign])


def rewrite_pipeline(
    path: str | os.PathLike,
    out: str | os.PathLike,
    formats: str | Sequence[str],
    metadata: Mapping[str, Any] | None = None,
    tolerance: float = TOLERANCE,
    dtype: str | None = None,
) -> dict[str, Any]:
    """Write the TorchScript pipeline file ``path`` again in ``formats`` beside ``out``
    (:func:`~phm_torch.online.formats.write_checked`), from its eager pipeline, with the file's metadata (updated
    by ``metadata``). The converted pipeline must equal the file within ``tolerance`` (|difference| / max(1, |file|),
    :func:`~.output_diffs.output_diffs`) on :func:`probe_records` (``ValueError`` otherwise, before anything is written); no output
    may replace the input file. ``dtype``: the files compute in it (:func:`~.formats.in_dtype`; None: the file's own).

    Returns ``{"files", "max_abs_diff_input"`` (per output, converted vs the file), ``"max_scaled_diff_input"``,
    ``"max_abs_diff_by_format"`` (each written file reloaded vs the converted pipeline, :func:`write_checked`),
    ``"derived"`` (state the file lacks, derived by the constructor)}.
    """
    from .formats import check_formats, format_path, in_dtype, write_checked

    names = check_formats(formats)
    path = Path(path)
    module = load_scripted(path)
    for name in names:
        if format_path(out, name).resolve() == path.resolve():
            raise ValueError(f"out: the {name!r} file {str(format_path(out, name))!r} would replace the input pipeline")
    pipeline, derived = convert_scripted(module, path)
    probe = probe_records(pipeline)
    with torch.no_grad():
        diffs = output_diffs(pipeline, module, probe)
    worst = max(d["scaled"] for name, d in diffs.items() if name != "noise")  # the estimator may be newer
    if not worst <= tolerance:
        raise ValueError(
            f"pipeline: {str(path)!r} converted to this phm_torch's OnlinePipeline differs from the file by {worst:.3g} "
            f"(> {tolerance:g}, relative above 1) on its probe records; not written"
        )
    kept = {k: v for k, v in read_metadata(path).items() if k not in ("format", "pipeline")}  # the writers add these
    pipeline = in_dtype(pipeline, dtype)
    checked = write_checked(pipeline, out, names, {**kept, **dict(metadata or {})}, probe)
    return {
        "files": checked["files"],
        "max_abs_diff_input": {name: d["abs"] for name, d in diffs.items()},
        "max_scaled_diff_input": worst,
        "max_abs_diff_by_format": checked["max_abs_diff"],
        "derived": derived,
    }


def rewrite_arguments(description: str) -> argparse.ArgumentParser:
    """The command line of a script that gives a pipeline file metadata measured on a store (``--pipeline``,
    ``--data-dir``, ``--out``, ``--split``, ``--formats``, ``--seed``); :func:`rewrite_with_report` writes it."""
    ap = argparse.ArgumentParser(description=description, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--pipeline", required=True, type=Path, help="the TorchScript pipeline file")
    ap.add_argument("--data-dir", required=True, type=Path, help="an independent store of its actuator and command")
    ap.add_argument("--out", required=True, type=Path, help="the pipeline written (.pt; .pt2 beside it)")
    ap.add_argument("--split", default="val")
    ap.add_argument("--formats", default="torchscript,export", help="comma-separated phm-export formats")
    ap.add_argument("--seed", type=int, default=0, help="seeds the added noise")
    return ap


def rewrite_with_report(
    path: str | os.PathLike,
    out: str | os.PathLike,
    formats: str,
    metadata: Mapping[str, Any],
    figures: Mapping[str, Any],
) -> dict[str, Any]:
    """A script's last step that gives a pipeline file ``path`` new ``metadata``: :func:`rewrite_pipeline` beside ``out``
    in the comma-separated ``formats``, and the report (``figures`` with the input and the files written) as
    ``<out stem>.<report name>.json``, ``figures["report"]`` naming it; returns the report."""
    from ..io.atomic import write_json

    written = rewrite_pipeline(path, out, [f.strip() for f in formats.split(",") if f.strip()], metadata)
    report = {k: v for k, v in figures.items() if k != "report"}
    report.update(pipeline=str(path), files=written["files"])
    write_json(Path(out).with_suffix(f".{figures['report']}.json"), report)
    return report
