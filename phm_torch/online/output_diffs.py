"""How far apart two forms of one online pipeline are (an exported file against its eager pipeline, two formats,
a TorchScript file against the pipeline rebuilt from it): the largest differences per output, NaN-aware."""

from __future__ import annotations

import math
from typing import Any

import torch


def max_difference(a: torch.Tensor, b: torch.Tensor) -> float:
    """The largest |a - b| over every value; NaN on both sides counts as equal, on one side only as infinite."""
    a, b = a.double(), b.double()
    same_nan = torch.isnan(a) & torch.isnan(b)
    return float(torch.where(same_nan, torch.zeros_like(a), (a - b).abs().nan_to_num(float("inf"))).max())


OUTPUTS = ("k_hat", "k_lower", "k_upper", "score", "p_faulty", "rul", "ood", "residual", "noise")  # StepResult's


def scaled_differences(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Per record (B,): the largest |a - b| / max(1, |b|) over the values of one output a, b (B, ...) (relative above
    1, e.g. the RUL in hours); NaN on both sides counts as equal, on one side only as an infinite difference."""
    a, b = a.double().reshape(a.shape[0], -1), b.double().reshape(b.shape[0], -1)
    scale = b.abs().nan_to_num(0.0, 0.0, 0.0).clamp(min=1.0)
    d = ((a - b) / scale).abs().nan_to_num(float("inf"))
    return torch.where(torch.isnan(a) & torch.isnan(b), torch.zeros_like(d), d).amax(1)


def output_diffs(a: Any, b: Any, x: torch.Tensor) -> dict[str, dict[str, float]]:
    """How far apart two pipelines (loaded, eager or scripted) are on records x (full, and for full x also their
    selected samples), over every output phm-predict reads (:data:`OUTPUTS`, the fields of
    :class:`~phm_torch.online.loaded.StepResult`): per output, ``abs`` the largest |a - b| and ``scaled`` the
    largest |a - b| / max(1, |b|) (relative for outputs above 1, e.g. the RUL in hours). NaN on both sides counts as
    equal, on one side only (or an output one of them lacks) as an infinite difference."""
    from .loaded import as_loaded  # here: loaded reads files of every format, this module none

    a, b = as_loaded(a), as_loaded(b)
    inputs = [x]
    if x.shape[1] == int(a.n_full):  # a TorchScript pipeline's selected samples are its gappy layer's
        inputs.append(x.index_select(1, a.indices if hasattr(a, "indices") else a.gappy.indices))
    out = {name: {"abs": 0.0, "scaled": 0.0} for name in OUTPUTS}
    for xi in inputs:
        ra, rb = a.run(xi), b.run(xi)
        bounds = {}
        if ra.k_lower is not None and bool(torch.isfinite(rb.noise).all()) and hasattr(a, "module"):
            # the intervals at b's noise estimate: the estimator is the code's, not the file's (noise_level became
            # the windowed estimate after the pretrained file was written); the estimates are compared as "noise"
            lower, upper = a.module.k_interval(ra.k_hat, rb.noise.to(ra.k_hat.dtype))
            bounds = {"k_lower": lower, "k_upper": upper}
        for name in OUTPUTS:
            va, vb = bounds.get(name, getattr(ra, name)), getattr(rb, name)
            if va is None or vb is None:
                diff = scaled = 0.0 if va is None and vb is None else math.inf
            else:
                diff, scaled = max_difference(va, vb), float(scaled_differences(va, vb).max())
            out[name] = {"abs": max(out[name]["abs"], diff), "scaled": max(out[name]["scaled"], scaled)}
    return out
