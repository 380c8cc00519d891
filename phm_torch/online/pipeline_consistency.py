"""A consistency check for an exported pipeline that lacks one, built from the pipeline itself and a store.

Pipelines exported before the consistency check (:mod:`.consistency`), the shipped pretrained one among them, carry
no forward surrogate, and their bundle (its full POD basis) may be gone. What the check reads of the basis is on
board anyway: the POD mean and modes at the selected samples (the gappy layer's ``mean_hat``, ``modes_hat``) and at
every ``STRIDE``-th sample (the full-record check's ``mean_rows`` and its *orthonormalised* basis Q = modes R^-1 of
those rows). R is recovered by least squares on the samples the two sets share (every 80th for 1000 uniform samples
and a stride of 16), exactly for a basis of full rank there, so the modes at the rows are Q R.

:func:`attach_consistency` then fits the forward surrogate k -> coefficients on a store's records of the pipeline's
actuator (the targets the gappy estimates of their selected samples, the coefficients the FDI itself reads) and
puts an uncalibrated check into the pipeline; :func:`~.consistency.calibrate_consistency` sets its thresholds.
"""

from __future__ import annotations

from typing import Any

import torch
from torch import nn

from ..surrogates.forward import ForwardSurrogate, fit_forward_on_coefficients
from ..surrogates.full_signal_check import record_stride
from .consistency import ConsistencyCheck

BASIS_TOLERANCE = 1e-4  # largest relative misfit of the shared samples' modes accepted for the recovered basis


def pipeline_basis(pipeline: nn.Module) -> tuple[torch.Tensor, torch.Tensor]:
    """The POD mean (n_full,) [A] and modes (n_full, n_m) of ``pipeline`` at the rows a consistency check reads
    (its selected samples and every ``STRIDE``-th sample), NaN elsewhere (float64).

    Raises:
        ValueError: the pipeline has no full-record check, its rows are not every ``STRIDE``-th sample, the two
            sample sets share fewer samples than modes, or the recovered basis does not reproduce the shared ones.
    """
    check = getattr(pipeline, "full_check", None)
    if check is None or not hasattr(check, "basis"):
        raise ValueError("pipeline: no full-record check (its basis at the full-record rows is needed)")
    n_full = int(pipeline.n_full)
    rows = check.rows.to(torch.long)
    gappy = pipeline.gappy
    idx = gappy.indices.to(torch.long)
    q, modes_hat = check.basis.to(torch.float64), gappy.modes_hat.to(torch.float64)
    n_m = int(modes_hat.shape[1])
    stride = record_stride(n_full, n_m)
    if not torch.equal(rows, torch.arange(0, n_full, stride)):
        raise ValueError(f"pipeline: the full-record check's rows are not every {stride}th sample")
    row_of = {int(r): i for i, r in enumerate(rows.tolist())}
    shared = [(row_of[int(v)], j) for j, v in enumerate(idx.tolist()) if int(v) in row_of]
    if len(shared) < n_m:
        raise ValueError(
            f"pipeline: its selected samples and every {stride}th sample share {len(shared)} samples, fewer than "
            f"its {n_m} modes: the basis at the rows cannot be recovered"
        )
    ri, ji = (torch.tensor(v) for v in zip(*shared))
    r = torch.linalg.lstsq(q[ri], modes_hat[ji]).solution  # (n_m, n_m)
    misfit = float((q[ri] @ r - modes_hat[ji]).abs().max() / modes_hat[ji].abs().max().clamp_min(1e-30))
    if misfit > BASIS_TOLERANCE:
        raise ValueError(f"pipeline: the full-record basis does not span the gappy modes (misfit {misfit:.2e})")
    mean = torch.full((n_full,), float("nan"), dtype=torch.float64)
    modes = torch.full((n_full, n_m), float("nan"), dtype=torch.float64)
    mean[rows], modes[rows] = check.mean_rows.to(torch.float64), q @ r
    mean[idx], modes[idx] = gappy.mean_hat.to(torch.float64), modes_hat
    return mean, modes


@torch.no_grad()
def attach_consistency(
    pipeline: nn.Module,
    k: torch.Tensor,
    current: torch.Tensor,
    nominal: torch.Tensor | None = None,
    seed: int = 13,
    **params: Any,
) -> ForwardSurrogate:
    """Fit a forward surrogate on records of the pipeline's actuator and put an uncalibrated consistency check
    into ``pipeline`` (an eager :class:`~.pipeline.OnlinePipeline`), replacing any it had; returns the surrogate.

    Args:
        k: (N, 8) fault vectors.  current: (N, n_full) their noise-free records [A].
        nominal: (8,) nominal fault vector (centres the eccentricity features).  seed, params: the surrogate's.
    """
    mean, modes = pipeline_basis(pipeline)
    dtype = pipeline.gappy.modes_hat.dtype
    gappy = pipeline.gappy
    alpha = torch.cat([gappy(gappy.select(block.to(dtype)))[0] for block in current.split(2048)])
    model = fit_forward_on_coefficients(
        alpha, k, current, gappy, pipeline.fdi, mean.to(dtype), modes.to(dtype), nominal, seed, **params
    )
    pipeline.consistency_check = ConsistencyCheck(model, mean.to(dtype), modes.to(dtype), gappy.indices)
    pipeline.has_consistency = True
    return model
