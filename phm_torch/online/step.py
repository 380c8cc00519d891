"""The whole online step as one traceable ``forward``: what ``torch.export`` (and AOTInductor) capture.

:class:`OnlineStep` wraps an :class:`~phm_torch.online.pipeline.OnlinePipeline` for one input length (full
records (B, n_full) or selected samples (B, n_points)) and returns every output phm-predict reads as a flat
tuple of tensors (``STEP_OUTPUTS``), computed with the pipeline's own submodules and buffers, so it equals the
pipeline's ``forward`` + ``k_interval`` + ``faulty_probability`` + ``noise_level`` + ``consistency`` and the
reasons of :func:`~phm_torch.online.input_contract.pipeline_reasons` (no submodule access needed afterwards).

What the eager pipeline decides with Python control flow on data, the step decides with tensors:

* the complete-record fast path of the gappy layer against its masked least squares ("every sample present" in
  the batch): a ``torch.cond`` whose branches take the layer's buffers as operands (:class:`_GappyBuffers`), so a
  complete batch never builds the masked system (:func:`masked_gappy` replays ``GappyPOD.forward``'s choice
  between the Woodbury update, at a fixed ``WOODBURY_MAX`` rows, and the per-signal Cholesky solve). A Bayesian
  layer, and the complete-record-only programs of ONNX and ExecuTorch, keep straight-line graphs (both paths
  selected with ``torch.where``, or the complete one alone);
* the RUL event search is the pipeline's own (:meth:`OnlinePipeline.rul_shifted`: a constant coarse grid and
  bisection count), called with ``blocked=False`` so that the classifier scores every row at once (the
  pipeline's ``SCORE_BLOCK`` split is a cache optimisation that gives the same scores; a split into a
  data-dependent number of blocks cannot be traced);
* the noise estimate: one call over the batch (the pipeline's 64-row blocks give the same per-row values).
"""

from __future__ import annotations

import copy
from typing import Any

import torch
from torch import nn
from torch.nn import functional as F

from ..surrogates.augment import noise_from_parts, noise_spacing
from .input_contract import PIPELINE_CHECKS
from .pipeline import OnlinePipeline

# outputs of OnlineStep.forward, in order (the names phm-predict and the file's metadata use)
STEP_OUTPUTS = (
    "k_hat",
    "k_lower",
    "k_upper",
    "score",
    "p_faulty",
    "rul",
    "ood",
    "residual",
    "noise",
    "consistency",
    "reasons",
)


def masked_gappy(gappy: nn.Module, samples: torch.Tensor, mask: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """``gappy(samples, mask)`` (alpha (B, n_m), residual (B,)) of a ``GappyPOD``, without data-dependent Python
    control flow: every path it may take is computed and the one it would take is selected (per batch, as it
    decides). samples (B, n_w) [A], NaN = missing; mask (B, n_w) bool, False = missing."""
    centred = samples - gappy.mean_hat
    valid = torch.isfinite(centred) & mask
    n_w = gappy.modes_hat.shape[0]
    fast = F.linear(centred, gappy.solve_matrix)
    fast_resid = torch.linalg.vector_norm(centred - F.linear(fast, gappy.modes_hat), dim=-1) / n_w**0.5
    centred = torch.where(valid, centred, torch.zeros_like(centred))
    w = valid.to(samples.dtype)
    count = w.sum(-1)
    missing = ~valid
    vm = gappy.modes_hat.unsqueeze(0) * w.unsqueeze(-1)  # (B, n_w, n_m)
    if gappy.bayesian:  # as GappyPOD.forward: R restricted to the present samples, factorised in float64
        w64 = w.to(torch.float64)
        cov = gappy.noise_covariance.to(torch.float64) * (w64.unsqueeze(-1) * w64.unsqueeze(-2)) + torch.diag_embed(
            1.0 - w64
        )
        weighted = torch.cholesky_solve(vm.to(torch.float64), torch.linalg.cholesky(cov)).transpose(1, 2).to(vm.dtype)
    else:
        weighted = vm.transpose(1, 2)
    gram = weighted @ vm + torch.diag(gappy.prior_precision)
    alpha, resid = gappy._solve(gram, weighted @ centred.unsqueeze(-1), centred, w, count)
    rows = min(int(gappy.woodbury_max), n_w)
    if not gappy.bayesian and rows > 0:
        # rows past a signal's own missing count are zero in U: S is the identity there, as for the signals
        # with fewer missing samples than the batch's most in GappyPOD.forward
        w_alpha, w_resid, accurate = gappy._woodbury(centred, missing, rows, w, count)
        use = (missing.sum(-1).amax() <= gappy.woodbury_max) & accurate.all()
        alpha, resid = torch.where(use, w_alpha, alpha), torch.where(use, w_resid, resid)
    complete = valid.all()
    return torch.where(complete, fast, alpha), torch.where(complete, fast_resid, resid)


class _GappyBuffers:
    """A ``GappyPOD`` (non-Bayesian) whose buffers are the given tensors: its least-squares methods run on the
    operands of a ``torch.cond`` branch instead of lifting the module's buffers."""

    def __init__(
        self,
        layer: nn.Module,
        mean: torch.Tensor,
        modes: torch.Tensor,
        solve: torch.Tensor,
        gram_inverse: torch.Tensor,
        prior: torch.Tensor,
    ):
        self.mean_hat, self.modes_hat, self.solve_matrix = mean, modes, solve
        self.gram_inverse, self.prior_precision = gram_inverse, prior
        self.bayesian, self.ridge = False, float(layer.ridge)
        self.woodbury_max, self.woodbury_min_eigenvalue = int(layer.woodbury_max), float(layer.woodbury_min_eigenvalue)
        self._layer = type(layer)

    def _solve(self, *args: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        return self._layer._solve(self, *args)

    def _woodbury(self, *args: Any) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        return self._layer._woodbury(self, *args)


def _step_view(pipeline: OnlinePipeline) -> OnlinePipeline:
    """``pipeline`` sharing every part but the FDI-only fold (:meth:`OnlinePipeline.k_hat_of_samples`), which the step
    never calls: an exported program would carry its derived weights as constants (1.4 MB for the pretrained one)."""
    view = copy.copy(pipeline)
    view._modules = dict(pipeline._modules)  # a child table of its own: the pipeline itself is left as it is
    view._modules["folded_fdi"] = nn.Identity()
    return view


class OnlineStep(nn.Module):
    """One input length of an :class:`OnlinePipeline` as a single traceable ``forward``.

    Args:
        pipeline: the eager pipeline (put in eval mode; its numbers are not changed).
        full: True for full records (B, n_full), False for selected samples (B, n_points).
        complete_only: only the complete-record path (no masked least squares, no Cholesky: what runtimes
            without linear solves, e.g. ONNX, can run); equal to the pipeline only for records without a missing
            sample, which the caller must ensure.
    """

    def __init__(self, pipeline: OnlinePipeline, full: bool, complete_only: bool = False):
        super().__init__()
        if complete_only and pipeline.n_points < pipeline.min_count:
            raise ValueError(
                f"complete_only: the pipeline needs {pipeline.min_count} of its {pipeline.n_points} "
                f"samples, so every record takes its missing-sample path (no complete-record step)"
            )
        self.pipeline = _step_view(pipeline.eval())
        self.full = bool(full)
        self.complete_only = bool(complete_only)
        self.length = pipeline.n_full if full else pipeline.n_points
        self.register_buffer("phases", torch.arange(3) < 2)  # RUL 5 and 50 % of a faulty verdict
        self.estimate_noise = self.full and (pipeline.noise_aware or pipeline.residual_limit.levels.shape[0] > 1)
        self._gather_plan(pipeline)

    def _gather_plan(self, p: OnlinePipeline) -> None:
        """How the step reads a full record: each check's samples once, as strided slices where they are regular
        (the noise estimate's window and spacing, the residual and consistency rows: a compiled program loads a
        slice in vector steps, an index one sample at a time) and the full-record check's jittered pairs in one
        gather; the bench offset is subtracted from these reads only, not from the whole record."""
        n = p.n_full
        self.head = min(p.noise_window + 2, n)
        self.spacing = noise_spacing(n, p.noise_window)
        self.check_stride = 0
        pairs = torch.zeros(0, dtype=torch.long)
        if p.has_full_check:
            c = p.full_check
            stride = int(c.rows[1] - c.rows[0]) if c.rows.numel() > 1 else n
            if not torch.equal(c.rows.cpu(), torch.arange(0, n, stride)):
                raise ValueError("OnlineStep: the full-record check's rows must be every stride-th sample")
            self.check_stride = stride
            pairs = torch.stack([c.shape_rows, c.next_rows], 1).reshape(-1).cpu()
        self.register_buffer("pair_cols", pairs.to(p.gappy.indices.device))
        # the consistency check estimates a full record's noise over its own window: the same reads if equal
        self.shared_noise = not p.has_consistency or p.consistency_check.noise_window == p.noise_window

    def _score(self, k: torch.Tensor) -> torch.Tensor:
        """Verdict score minus threshold (N,) of fault vectors k (N, 8), all rows at once."""
        clf = self.pipeline.verdict_classifier
        return clf(k) - clf.threshold

    def _complete(self, samples: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
        """The pipeline's path for a batch with every sample present: (alpha, residual, enough, flat)."""
        g = self.pipeline.gappy
        return self._complete_of(samples, g.mean_hat, g.modes_hat, g.solve_matrix, g.gram_inverse, g.prior_precision)

    def _complete_of(
        self, samples: torch.Tensor, *buffers: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
        """:meth:`_complete` on the gappy layer's buffers given as operands (a ``torch.cond`` branch)."""
        layer = _GappyBuffers(self.pipeline.gappy, *buffers)
        centred = samples - layer.mean_hat
        alpha = F.linear(centred, layer.solve_matrix)
        resid = torch.linalg.vector_norm(centred - F.linear(alpha, layer.modes_hat), dim=-1)
        low, high = torch.aminmax(samples, dim=1)
        resid = resid / layer.modes_hat.shape[0] ** 0.5
        return alpha, resid, torch.ones_like(resid, dtype=torch.bool), (high - low) < 1e-6

    def _gappy_of(
        self, samples: torch.Tensor, *buffers: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
        """:meth:`_gappy` on the gappy layer's buffers given as operands (a ``torch.cond`` branch)."""
        return self._gappy(samples, _GappyBuffers(self.pipeline.gappy, *buffers))

    def _gappy(
        self, samples: torch.Tensor, layer: Any = None
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
        """The pipeline's path for a batch with missing samples: (alpha, residual, enough, flat); ``layer``: the
        gappy layer or its :class:`_GappyBuffers` (None: the pipeline's)."""
        p = self.pipeline
        layer = p.gappy if layer is None else layer
        valid = torch.isfinite(samples)
        enough = valid.sum(1) >= p.min_count
        filled = torch.where(enough.unsqueeze(1) & valid, samples, layer.mean_hat.expand_as(samples))
        mask = torch.where(enough.unsqueeze(1), valid, torch.ones_like(valid))
        alpha, resid = masked_gappy(layer, filled, mask)
        flat = torch.where(valid, samples, torch.zeros_like(samples)).std(1) < 1e-6
        return alpha, resid, enough, flat

    def forward(self, x: torch.Tensor, offset: torch.Tensor) -> tuple[torch.Tensor, ...]:
        """Args: x (B, length) current [A] as measured (NaN = missing); offset (length,) [A] subtracted before
        the pipeline (a bench's difference at nominal, ``bench_nominal - nominal_record``: the pipeline's
        ``rebase``; zeros for none).

        Returns ``STEP_OUTPUTS``: k_hat (B, 8); k_lower, k_upper (B, 8) its intervals (at the measured noise for
        full records, the first calibrated level for selected samples; NaN uncalibrated); verdict score (B,)
        (> 0 healthy); P(faulty) (B,) (NaN uncalibrated); RUL 5/50/95 % (B, 3) [h] (NaN out of distribution);
        out_of_distribution (B,) bool; gappy residual (B,) [A]; relative noise (B,) as measured, before the offset
        (NaN for selected samples); consistency (B,) (> 1 inconsistent, NaN without a forward surrogate);
        reasons (B, len(PIPELINE_CHECKS)) bool, which of the pipeline's checks fired.
        """
        p = self.pipeline
        dtype = p.times.dtype
        b = x.shape[0]
        false = torch.zeros(b, dtype=torch.bool, device=x.device)
        nan = torch.full((b,), float("nan"), dtype=dtype, device=x.device)
        x = x.to(dtype)
        if self.full:  # the records' reads (see _gather_plan); measured = the pipeline's noise_level
            offset = offset.to(dtype)
            head, spaced = x[:, : self.head], x[:, :: self.spacing]
            measured = noise_from_parts(head, spaced)
            estimate = noise_from_parts(head - offset[: self.head], spaced - offset[:: self.spacing])
            noise = estimate if self.estimate_noise else None
            idx = p.gappy.indices
            samples = x.index_select(1, idx) - offset.index_select(0, idx)
        else:
            estimate = None
            measured = nan
            x = x - offset.to(dtype)
            noise = None
            samples = x
        samples = samples.to(p.gappy.modes_hat.dtype)
        if self.complete_only:  # the caller guarantees every sample present (no linear solve in the graph)
            alpha, residual, enough, flat = self._complete(samples)
        elif p.n_points >= p.min_count and not p.gappy.bayesian:
            # the pipeline's choice as a graph branch: a complete batch never builds the masked least squares
            # (B, n_w, n_m). The layer's buffers go in as operands (a branch that lifts module buffers fails in
            # AOTInductor), and no transposed view of them is taken (torch.export hoists it out as an aliasing
            # operand): F.linear
            g = p.gappy
            alpha, residual, enough, flat = torch.cond(
                torch.isfinite(samples).all(),
                self._complete_of,
                self._gappy_of,
                (samples, g.mean_hat, g.modes_hat, g.solve_matrix, g.gram_inverse, g.prior_precision),
            )
        else:  # both paths, the pipeline's choice selected
            alpha, residual, enough, flat = self._gappy(samples)
            if p.n_points >= p.min_count:
                complete = torch.isfinite(samples).all()
                alpha, residual, enough, flat = (
                    torch.where(complete, a, b)
                    for a, b in zip(self._complete(samples), (alpha, residual, enough, flat))
                )
        k_hat = p.fdi(alpha, noise) if p.noise_aware else p.fdi(alpha)
        score = self._score(k_hat)
        if self.full and p.has_full_check:
            check = p.full_check
            rows = (x[:, :: self.check_stride] - offset[:: self.check_stride]).to(check.basis.dtype)
            both = (x.index_select(1, self.pair_cols) - offset.index_select(0, self.pair_cols)).to(check.basis.dtype)
            both = both.reshape(b, -1, 2)
            shape = both[:, :, 0]
            pod = check._residual(rows) > check.residual_threshold
            rough = check._roughness(shape, both[:, :, 1]) > check.roughness_threshold
            plateau = check._plateau(shape) > check.plateau_threshold
        else:
            pod, rough, plateau = false, false, false
        gappy_flag = (residual > p._limit(noise, residual)) | ~torch.isfinite(residual)
        if not p.has_consistency:
            consistency = nan
        elif self.full and estimate is not None and self.shared_noise:
            c = p.consistency_check
            level = estimate.to(c.mean_rows.dtype)
            y = x[:, :: c.stride] - offset[:: c.stride]
            consistency = c.rows_statistic(y, k_hat, level) / c.threshold(level, True)
        else:  # another noise window: the check reads the records itself
            consistency = p.consistency_check(x - offset if self.full else x, k_hat, noise)
        inconsistent = consistency > 1.0  # NaN (no finite sample, or no check) compares False
        flags = {
            "missing": ~enough,
            "flat": flat,
            "gappy_residual": gappy_flag,
            "pod_residual": pod,
            "roughness": rough,
            "plateau": plateau,
            "inconsistent": inconsistent,
        }
        reasons = torch.stack([flags[name] for name in PIPELINE_CHECKS], 1)
        ood = reasons.any(1)
        rul = p.rul(k_hat, True, blocked=False)
        rul = torch.where((score <= 0).unsqueeze(1) & self.phases, torch.zeros_like(rul), rul)
        rul = torch.where(ood.unsqueeze(1), torch.full_like(rul, float("nan")), rul)
        lower, upper = p.k_interval(k_hat, measured) if self.full else p.k_interval(k_hat)
        return (
            k_hat,
            lower,
            upper,
            score,
            p.faulty_probability(score),
            rul,
            ood,
            residual,
            measured,
            consistency,
            reasons,
        )
