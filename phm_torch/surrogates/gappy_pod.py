"""Gappy POD as a differentiable, batched least-squares layer.

Given the samples f_hat (B, n_w) of signals at the selected times, find the POD coefficients alpha
(B, n_m) that best explain them: minimise ||m * (f_hat - y0_hat - V_hat alpha)||^2, where V_hat (n_w, n_m)
holds the modes at the selected samples, y0_hat the mean signal there and m (B, n_w) marks the samples
that are present. The normal equations are the paper's G alpha = f with G = V_hat^T M V_hat and
f = V_hat^T M (f_hat - y0_hat) (the paper has no missing samples, M = I, and no centring term).

* A sample that is NaN/inf, or False in the optional mask, is dropped from that signal's system only.
  A signal whose remaining samples cannot determine the n_m coefficients (singular G, e.g. fewer
  present samples than modes) gets NaN coefficients and an infinite residual; the batch goes on.
* With every sample present the solution is one matrix product with the precomputed G^-1 V_hat^T
  (the online fast path); otherwise each signal gets its own G, solved batched by Cholesky.
* The layer is differentiable in the samples (and in its buffers if they are made parameters).
* It also returns the reconstruction residual, the RMS over the present samples of
  f_hat - y0_hat - V_hat alpha [signal unit]: zero when n_w = n_m; downstream it flags signals that the
  basis does not explain (out of distribution).
"""

from __future__ import annotations

import torch
from torch import nn


class GappyPOD(nn.Module):
    """``forward(samples, mask=None) -> (alpha, residual)``.

    Args:
        modes: (n_e, n_m) POD modes (or already (n_w, n_m) if ``indices`` is None).
        mean: (n_e,) mean signal y0 [signal unit] (or (n_w,)).
        indices: (n_w,) selected sample indices into n_e; ``None`` when modes/mean are already selected.
        ridge: Tikhonov term added to G as ``ridge * I`` (0 = the paper's plain least squares); set it > 0
            to solve signals with fewer present samples than modes (biased towards alpha = 0).

    Buffers: ``indices`` (n_w,) int64, ``modes_hat`` (n_w, n_m), ``mean_hat`` (n_w,), ``solve_matrix``
    (n_m, n_w) = G^-1 V_hat^T for the complete case (computed in float64).
    """

    def __init__(self, modes: torch.Tensor, mean: torch.Tensor, indices: torch.Tensor | None = None,
                 ridge: float = 0.0):
        super().__init__()
        if modes.ndim != 2:
            raise ValueError(f"modes must be (n_e, n_m), got shape {tuple(modes.shape)}")
        if mean.shape != modes.shape[:1]:
            raise ValueError(f"mean must have shape ({modes.shape[0]},) like the modes' first axis, "
                             f"got {tuple(mean.shape)}")
        if indices is None:
            indices = torch.arange(modes.shape[0])
        else:
            indices = torch.as_tensor(indices, dtype=torch.long).flatten()
            if indices.numel() == 0 or int(indices.min()) < 0 or int(indices.max()) >= modes.shape[0]:
                raise ValueError(f"indices must lie in [0, {modes.shape[0]}), got {indices.tolist()}")
            if indices.unique().numel() != indices.numel():
                raise ValueError("indices must be distinct")
            modes, mean = modes[indices], mean[indices]
        if not ridge >= 0.0:
            raise ValueError(f"gappy.ridge must be >= 0, got {ridge!r}")
        n_w, n_m = modes.shape
        if n_w < n_m and ridge == 0.0:
            raise ValueError(f"gappy POD needs at least as many samples as modes: n_points={n_w} < n_modes={n_m} "
                             f"(or set a ridge > 0)")
        self.ridge = float(ridge)
        self.register_buffer("indices", indices.clone())
        self.register_buffer("modes_hat", modes.detach().clone().contiguous())
        self.register_buffer("mean_hat", mean.detach().clone())
        v = modes.detach().to(torch.float64)
        gram = v.T @ v + self.ridge * torch.eye(n_m, dtype=torch.float64)
        self.register_buffer("solve_matrix", torch.linalg.solve(gram, v.T).to(modes.dtype).contiguous())

    @property
    def n_points(self) -> int:
        return self.modes_hat.shape[0]

    @property
    def n_modes(self) -> int:
        return self.modes_hat.shape[1]

    def select(self, signals: torch.Tensor) -> torch.Tensor:
        """The samples (..., n_w) at the selected indices of full signals (..., n_e)."""
        return signals.index_select(-1, self.indices)

    def forward(self, samples: torch.Tensor, mask: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        """POD coefficients from the selected samples.

        Args:
            samples: (B, n_w) values at the selected times [signal unit]; NaN/inf = missing.
            mask: optional (B, n_w) bool, False = missing.

        Returns:
            alpha (B, n_m) and residual (B,) [signal unit, RMS over the present samples].
        """
        if samples.dim() != 2 or samples.shape[1] != self.modes_hat.shape[0]:
            raise ValueError(f"samples must be (B, {self.modes_hat.shape[0]}), got {list(samples.shape)}")
        valid = torch.isfinite(samples)
        if mask is not None:
            valid = valid & mask
        centred = torch.where(valid, samples - self.mean_hat, torch.zeros_like(samples))
        if bool(valid.all()):
            alpha = centred @ self.solve_matrix.T
            resid = centred - alpha @ self.modes_hat.T
            return alpha, resid.pow(2).mean(-1).sqrt()
        w = valid.to(samples.dtype)
        count = w.sum(-1)
        vm = self.modes_hat.unsqueeze(0) * w.unsqueeze(-1)                        # (B, n_w, n_m)
        gram = vm.transpose(1, 2) @ vm
        eye = torch.eye(gram.shape[-1], dtype=gram.dtype, device=gram.device)
        if self.ridge > 0.0:
            gram = gram + self.ridge * eye
        rhs = vm.transpose(1, 2) @ centred.unsqueeze(-1)                          # (B, n_m, 1)
        factor, info = torch.linalg.cholesky_ex(gram)
        pivots = torch.diagonal(factor, dim1=-2, dim2=-1)
        # Numerically singular too: squared pivot ratio (~ 1 / cond G) below n_m machine epsilons.
        eps = 2.220446049250313e-16 if gram.dtype == torch.float64 else 1.1920928955078125e-07
        ok = (info == 0) & ((pivots.amin(-1) / pivots.amax(-1)).pow(2) > gram.shape[-1] * eps)
        if self.ridge == 0.0:
            ok = ok & (count >= gram.shape[-1])
        # A signal whose present samples cannot determine the modes gets NaN coefficients and an infinite
        # residual (flagged out of distribution) instead of failing the batch; its system is replaced by
        # the identity so that no NaN reaches the gradients of the others.
        chol = torch.linalg.cholesky(torch.where(ok.reshape(-1, 1, 1), gram, eye))
        alpha = torch.cholesky_solve(rhs, chol).squeeze(-1)
        resid = (centred - alpha @ self.modes_hat.T) * w
        resid = (resid.pow(2).sum(-1) / count.clamp(min=1.0)).sqrt()
        alpha = torch.where(ok.unsqueeze(-1), alpha, torch.full_like(alpha, float("nan")))
        return alpha, torch.where(ok, resid, torch.full_like(resid, float("inf")))

    def reconstruct(self, alpha: torch.Tensor) -> torch.Tensor:
        """The fitted values (B, n_w) at the selected samples."""
        return self.mean_hat + alpha @ self.modes_hat.T

    def condition_number(self) -> float:
        """2-norm condition number of the complete gappy matrix G = V_hat^T V_hat (+ ridge I)."""
        v = self.modes_hat.to(torch.float64)
        gram = v.T @ v + self.ridge * torch.eye(v.shape[1], dtype=torch.float64)
        return float(torch.linalg.cond(gram))

    def extra_repr(self) -> str:
        return f"n_points={self.n_points}, n_modes={self.n_modes}, ridge={self.ridge}"
