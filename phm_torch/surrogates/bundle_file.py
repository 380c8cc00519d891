"""The surrogate bundle's file format: writing, reading and checking it, and rebuilding its parts.

Plain functions on the file's two blocks (``meta``, ``tensors``), so that :class:`~.bundle.SurrogateBundle`
keeps only the gathering of its own attributes; this module does not import :mod:`.bundle` (no cycle):

* ``write_bundle_file(path, meta, tensors) -> Path``: the container, written atomically;
* ``read_bundle_file(path, expect=None, map_location="cpu") -> (meta, tensors)``: read and checked (format,
  version, required meta, the caller's ``expect``);
* ``rebuild_parts(meta, tensors, path) -> dict``: the POD, FDI network, classifiers and forward model.

File format (``save``/``load``): one ``torch.save`` file holding only plain containers of str, int,
float, bool, None and tensors, read back with ``torch.load(weights_only=True)`` (never unpickled)::

    {"format": "phm_torch.surrogate_bundle", "version": 1,
     "meta": {"n_samples", "n_modes", "n_points", "n_hidden", "n_layers", "n_members", "input_scaling",
              "noise_input", "default_noise", "max_noise", "sample_rate", "signal", "unit",
              "fault_names", "health_convention", "selector": {"name", "params"},
              "classifier": {"name", "params"}, "verdict_classifier": {"name", "params"} or None,
              "forward_model": {ForwardSurrogate params} or None (absent: older bundles),
              "gappy_ridge", "phm_torch_version", "extra": {...}},
     "tensors": {"pod.mean_", "pod.modes_", "pod.singular_values_", "pod.energy_", "indices",
                 "sample_times", "residual_threshold", "network.<state_dict>", "classifier.<state_dict>",
                 "verdict_classifier.<state_dict>" and "forward_model.<state_dict>" (when it has them), and, for a Bayesian gappy layer,
                 "gappy.noise_covariance", "gappy.prior_variance",
                 and, when the store had one, "nominal_record"}}
"""

from __future__ import annotations

import io
import os
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import torch

from ..io.atomic import atomic_open
from .classifiers import HealthClassifier, build_classifier
from .fdi_ensemble import build_fdi_network
from .forward import ForwardSurrogate
from .pod import POD

FORMAT = "phm_torch.surrogate_bundle"
VERSION = 1
COMPARED = ("n_samples", "n_modes", "n_points", "n_hidden", "n_layers", "n_members")


def write_bundle_file(path: str | os.PathLike, meta: Mapping[str, Any], tensors: Mapping[str, torch.Tensor]) -> Path:
    """Write ``{"format", "version", "meta", "tensors"}`` atomically to ``path``; return it as a Path.

    Args:
        meta: the plain JSON-able ``meta`` block (:meth:`~.bundle.SurrogateBundle.metadata`).
        tensors: name -> CPU tensor, the ``tensors`` block (names as in the module docstring).
    """
    # serialised before the file is opened: a container torch.save rejects creates no file nor directory
    buf = io.BytesIO()
    torch.save({"format": FORMAT, "version": VERSION, "meta": meta, "tensors": tensors}, buf)
    path = Path(path)
    with atomic_open(path, "wb") as fh:
        fh.write(buf.getvalue())
    return path


def read_bundle_file(
    path: str | os.PathLike, expect: Mapping[str, Any] | None = None, map_location: str | torch.device = "cpu"
) -> tuple[dict[str, Any], dict[str, torch.Tensor]]:
    """Read and check a bundle file (``weights_only=True``): its ``(meta, tensors)`` blocks.

    ``meta`` (dict) gets the defaults of bundles written before ``n_layers``/``n_members``/``noise_input``
    existed; ``tensors`` is name -> tensor on ``map_location``.

    Args:
        expect: values the caller's configuration requires, e.g. ``{"n_modes": 22, "n_points": 30}``
            (keys among :data:`COMPARED`; None values are not compared).

    Raises:
        ValueError: a missing or unreadable file, another format or version, an incomplete ``meta``, an
            unknown ``expect`` key, or a mismatch with ``expect`` (naming the field).
    """
    path = Path(path)
    if not path.is_file():
        raise ValueError(f"surrogate bundle {str(path)!r} does not exist")
    try:
        blob = torch.load(path, map_location=map_location, weights_only=True)
    except Exception as e:  # noqa: BLE001 - any unreadable file is the same user error
        raise ValueError(f"{path}: not a readable surrogate bundle ({type(e).__name__}: {e})") from None
    if not isinstance(blob, dict) or blob.get("format") != FORMAT:
        raise ValueError(
            f"{path}: not a surrogate bundle (format {blob.get('format') if isinstance(blob, dict) else None!r}, "
            f"expected {FORMAT!r})"
        )
    if blob.get("version") != VERSION:
        raise ValueError(f"{path}: bundle version {blob.get('version')!r} is not supported (expected {VERSION})")
    meta, t = blob.get("meta"), blob.get("tensors")
    if isinstance(meta, dict):
        meta.setdefault("n_layers", 1)  # bundles written before the options: one network
        meta.setdefault("n_members", 1)  # of one hidden layer, not noise-aware
        meta.setdefault("noise_input", False)
    required = (*COMPARED, "input_scaling", "sample_rate", "selector", "classifier", "gappy_ridge", "extra")
    missing = [k for k in required if not isinstance(meta, dict) or k not in meta]
    if missing or not isinstance(t, dict):
        raise ValueError(f"{path}: incomplete surrogate bundle (meta lacks {missing})")
    for key, want in (expect or {}).items():
        if key not in COMPARED:
            raise ValueError(f"expect: unknown field {key!r}; known: {list(COMPARED)}")
        if want is not None and meta[key] != want:
            raise ValueError(
                f"{path}: bundle from another configuration: {key}={meta[key]} in the file, {want} expected"
            )
    return meta, t


def rebuild_parts(meta: Mapping[str, Any], tensors: Mapping[str, torch.Tensor], path: Path) -> dict[str, Any]:
    """The trained parts of a bundle, rebuilt from the checked ``meta`` and ``tensors`` of :func:`read_bundle_file`.

    Returns:
        ``{"pod": POD (n_e samples, n_m modes), "network": FDIMLP | FDIEnsemble (n_m inputs),
        "classifier": HealthClassifier, "verdict_classifier": HealthClassifier | None,
        "forward_model": ForwardSurrogate (in eval mode) | None}``; ``path`` only names the file in errors.

    Raises:
        ValueError: the POD modes disagree with ``meta``, or a classifier or the forward model cannot be
            rebuilt from its spec and tensors.
    """
    t = tensors
    n_m = meta["n_modes"]
    pod = POD(n_m)
    for k in ("mean_", "modes_", "singular_values_", "energy_"):
        setattr(pod, k, t[f"pod.{k}"])
    if tuple(pod.modes_.shape) != (meta["n_samples"], n_m):
        raise ValueError(
            f"{path}: pod.modes_ has shape {tuple(pod.modes_.shape)}, meta says ({meta['n_samples']}, {n_m})"
        )
    # bundles written before the noise-aware network lack these; the network's defaults apply
    noise_kwargs = {k: meta[k] for k in ("default_noise", "max_noise") if k in meta}
    network = build_fdi_network(
        n_m,
        meta["n_hidden"],
        meta["n_layers"],
        meta["n_members"],
        input_scaling=meta["input_scaling"],
        noise_input=meta["noise_input"],
        **noise_kwargs,
    )
    network.load_state_dict(_prefixed(t, "network."))
    classifier = _classifier(meta["classifier"], _prefixed(t, "classifier."), path)
    verdict_spec = meta.get("verdict_classifier")
    verdict = None if verdict_spec is None else _classifier(verdict_spec, _prefixed(t, "verdict_classifier."), path)
    forward_model = None
    if meta.get("forward_model") is not None:
        try:
            forward_model = ForwardSurrogate(**meta["forward_model"])
            forward_model.load_state_dict(_prefixed(t, "forward_model."))
        except (TypeError, ValueError, RuntimeError) as e:
            raise ValueError(f"{path}: forward_model: {e}") from None
    return {
        "pod": pod,
        "network": network,
        "classifier": classifier,
        "verdict_classifier": verdict,
        "forward_model": forward_model.eval() if forward_model else None,
    }


def _spec(classifier: HealthClassifier | None) -> dict[str, Any] | None:
    return None if classifier is None else {"name": classifier.name, "params": classifier.get_params()}


def _classifier(spec: Mapping[str, Any], state: Mapping[str, torch.Tensor], path: Path) -> HealthClassifier:
    """A fitted classifier rebuilt from its spec ``{"name", "params"}`` and its saved buffers."""
    try:
        classifier = build_classifier(spec["name"], **spec["params"])
    except ValueError as e:
        raise ValueError(f"{path}: {e}") from None
    known = dict(classifier.named_buffers())
    if set(state) != set(known):
        raise ValueError(f"{path}: classifier tensors {sorted(state)} do not match {spec['name']}'s {sorted(known)}")
    for k, v in state.items():  # fitted buffers may have other shapes than the unfitted twin's
        owner, _, name = k.rpartition(".")  # a submodule's buffer (dotted name) is set on it
        setattr(classifier.get_submodule(owner) if owner else classifier, name, v)
    return classifier


def _prefixed(tensors: Mapping[str, torch.Tensor], prefix: str) -> dict[str, torch.Tensor]:
    return {k[len(prefix) :]: v for k, v in tensors.items() if k.startswith(prefix)}
