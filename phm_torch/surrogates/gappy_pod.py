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
  (the online fast path); otherwise each signal gets its own G, solved batched by Cholesky. For least
  squares with few samples missing (at most ``WOODBURY_MAX`` in any signal of the batch), G is the
  complete matrix minus the outer products of the k missing rows U (k, n_m), and the Woodbury identity
  gives G^-1 from the precomputed complete inverse and one k x k system S = I - U G^-1 U^T per signal:
  end-to-end training (a few dropped samples per record) then costs little more than the fast path,
  with hundreds of samples per record as with thirty (a per-signal G costs n_w x n_m x n_m). Where some
  S is nearly singular (the dropped samples held modes no other sample sees) the batch is solved per
  signal, which also decides what is singular.
* The layer is differentiable in the samples (and in its buffers if they are made parameters).
* It also returns the reconstruction residual, the RMS over the present samples of
  f_hat - y0_hat - V_hat alpha [signal unit]: zero when n_w = n_m (plain least squares); downstream it
  flags signals that the basis does not explain (out of distribution).

Bayesian variant (``noise_covariance`` R and ``prior_variance`` lambda, from :func:`gappy_statistics`):
the samples are f_hat = y0_hat + V_hat alpha + e, where e is what the n_m modes leave out (the truncated
modes, seen at the selected samples, plus measurement noise) with covariance R, and alpha has the prior
variance lambda of the training coefficients. The estimate is the posterior mean

    alpha = (V_hat^T R^-1 V_hat + diag(1 / lambda))^-1 V_hat^T R^-1 (f_hat - y0_hat),

the linear minimum-mean-square-error estimator. With R and lambda the covariances of the training
snapshots themselves, it is exactly the least-squares regression of the training coefficients on their
samples (tested). Plain least squares treats the truncated modes as white noise and lets them alias
into alpha; on the paper store (22 modes, 30 SOM points) it halves err_alpha, 6.5 % -> 3.2 %. A missing
sample drops its row and column of R.
"""

from __future__ import annotations

import torch
from torch import nn
from torch.nn import functional as F

# most missing samples per signal solved by the Woodbury identity (k x k systems); more: a G per signal
WOODBURY_MAX = 8
# smallest eigenvalue of S = I - U G^-1 U^T for the update (float32 loses eps / lambda_min(S) of alpha)
WOODBURY_MIN_EIGENVALUE = 1e-3


class GappyPOD(nn.Module):
    """``forward(samples, mask=None) -> (alpha, residual)``.

    Args:
        modes: (n_e, n_m) POD modes (or already (n_w, n_m) if ``indices`` is None).
        mean: (n_e,) mean signal y0 [signal unit] (or (n_w,)).
        indices: (n_w,) selected sample indices into n_e; ``None`` when modes/mean are already selected.
        ridge: Tikhonov term added to G as ``ridge * I`` (0 = the paper's plain least squares); set it > 0
            to solve signals with fewer present samples than modes (biased towards alpha = 0).
        noise_covariance: (n_w, n_w) covariance R of the unexplained part of the samples [signal unit^2];
            with ``prior_variance``, the Bayesian estimator (module docstring). None = plain least squares.
        prior_variance: (n_m,) prior variance lambda of the coefficients [signal unit^2], > 0.

    Buffers: ``indices`` (n_w,) int64, ``modes_hat`` (n_w, n_m), ``mean_hat`` (n_w,), ``solve_matrix``
    (n_m, n_w) = G^-1 V_hat^T R^-1 for the complete case (computed in float64), ``noise_covariance``
    (n_w, n_w) (empty, (0, 0), for least squares), ``prior_precision`` (n_m,) (1 / lambda + ridge) and
    ``gram_inverse`` (n_m, n_m), the inverse of the complete G.
    """

    def __init__(
        self,
        modes: torch.Tensor,
        mean: torch.Tensor,
        indices: torch.Tensor | None = None,
        ridge: float = 0.0,
        noise_covariance: torch.Tensor | None = None,
        prior_variance: torch.Tensor | None = None,
    ):
        super().__init__()
        if modes.ndim != 2:
            raise ValueError(f"modes must be (n_e, n_m), got shape {tuple(modes.shape)}")
        if mean.shape != modes.shape[:1]:
            raise ValueError(
                f"mean must have shape ({modes.shape[0]},) like the modes' first axis, got {tuple(mean.shape)}"
            )
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
        if (noise_covariance is None) != (prior_variance is None):
            raise ValueError("gappy POD: give both noise_covariance and prior_variance (Bayesian) or neither")
        self.bayesian = noise_covariance is not None
        if n_w < n_m and ridge == 0.0 and not self.bayesian:
            raise ValueError(
                f"gappy POD needs at least as many samples as modes: n_points={n_w} < n_modes={n_m} "
                f"(or set a ridge > 0)"
            )
        self.ridge = float(ridge)
        if noise_covariance is None or prior_variance is None:
            cov = torch.eye(n_w, dtype=torch.float64)
            precision = torch.full((n_m,), self.ridge, dtype=torch.float64)
        else:
            cov, lam = noise_covariance.detach().to(torch.float64), prior_variance.detach().to(torch.float64)
            if cov.shape != (n_w, n_w) or lam.shape != (n_m,):
                raise ValueError(
                    f"gappy POD: noise_covariance must be ({n_w}, {n_w}) and prior_variance ({n_m},), "
                    f"got {tuple(cov.shape)} and {tuple(lam.shape)}"
                )
            if not bool((lam > 0).all()) or torch.linalg.cholesky_ex(cov)[1] != 0:
                raise ValueError("gappy POD: prior_variance must be > 0 and noise_covariance positive definite")
            precision = 1.0 / lam + self.ridge
        self.register_buffer("indices", indices.clone())
        self.register_buffer("modes_hat", modes.detach().clone().contiguous())
        self.register_buffer("mean_hat", mean.detach().clone())
        # least squares needs no R: an (n_w, n_w) identity would be most of an exported pipeline at 1000 samples
        self.register_buffer(
            "noise_covariance",
            cov.to(modes.dtype).contiguous() if self.bayesian else torch.zeros(0, 0, dtype=modes.dtype),
        )
        self.register_buffer("prior_precision", precision.to(modes.dtype))
        v = modes.detach().to(torch.float64)
        weighted = torch.linalg.solve(cov, v).T  # V_hat^T R^-1 (n_m, n_w)
        gram = self._gram(v, weighted, precision)
        self.register_buffer("solve_matrix", torch.linalg.solve(gram, weighted).to(modes.dtype).contiguous())
        self.register_buffer("gram_inverse", torch.linalg.inv(gram).to(modes.dtype).contiguous())
        self.woodbury_max, self.woodbury_min_eigenvalue = WOODBURY_MAX, WOODBURY_MIN_EIGENVALUE

    @staticmethod
    def _gram(v: torch.Tensor, weighted: torch.Tensor, precision: torch.Tensor) -> torch.Tensor:
        """G = V_hat^T R^-1 V_hat + diag(prior precision), float64."""
        return weighted @ v + torch.diag(precision)

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
        centred = samples - self.mean_hat
        valid = torch.isfinite(centred)
        if mask is not None:
            valid = valid & mask
        if bool(valid.all()):  # the online fast path: few passes over the (B, n_w) samples
            alpha = F.linear(centred, self.solve_matrix)
            resid = torch.linalg.vector_norm(centred - F.linear(alpha, self.modes_hat), dim=-1)
            return alpha, resid / self.modes_hat.shape[0] ** 0.5
        centred = torch.where(valid, centred, torch.zeros_like(centred))
        w = valid.to(samples.dtype)
        count = w.sum(-1)
        missing = ~valid
        most = int(missing.sum(-1).max())
        if not self.bayesian and most <= self.woodbury_max:
            alpha, resid, accurate = self._woodbury(centred, missing, most, w, count)
            if bool(accurate.all()):
                return alpha, resid
        vm = self.modes_hat.unsqueeze(0) * w.unsqueeze(-1)  # (B, n_w, n_m)
        if self.bayesian:  # R restricted to the present samples (identity rows/columns for the missing),
            # factorised in float64: R's spread of scales (truncated modes + noise) can defeat float32
            w64 = w.to(torch.float64)
            cov = self.noise_covariance.to(torch.float64) * (w64.unsqueeze(-1) * w64.unsqueeze(-2)) + torch.diag_embed(
                1.0 - w64
            )
            weighted = torch.cholesky_solve(vm.to(torch.float64), torch.linalg.cholesky(cov))
            weighted = weighted.transpose(1, 2).to(vm.dtype)  # (B, n_m, n_w)
        else:
            weighted = vm.transpose(1, 2)
        gram = weighted @ vm + torch.diag(self.prior_precision)
        return self._solve(gram, weighted @ centred.unsqueeze(-1), centred, w, count)

    def _woodbury(
        self, centred: torch.Tensor, missing: torch.Tensor, most: int, w: torch.Tensor, count: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Least squares without the (at most ``most``) missing samples of each signal, by the Woodbury
        identity on the complete G^-1 (module docstring); arguments as :meth:`_solve`. Returns alpha,
        residual and whether each signal's S is far enough from singular for the update to be accurate
        (its smallest eigenvalue, which G_s's conditioning divides, above ``WOODBURY_MIN_EIGENVALUE``);
        the caller solves the batch per signal otherwise, which also decides what is singular."""
        rows = torch.topk(missing.to(centred.dtype), most, dim=-1).indices  # (B, k)
        u = self.modes_hat[rows] * missing.gather(-1, rows).to(centred.dtype).unsqueeze(-1)  # (B, k, n_m)
        a0 = F.linear(centred, self.solve_matrix)  # G^-1 rhs (B, n_m)
        wu = u @ self.gram_inverse  # U G^-1 (B, k, n_m)
        eye = torch.eye(most, dtype=centred.dtype, device=centred.device)
        small = eye - wu @ u.transpose(1, 2)  # S (B, k, k)
        factor, info = torch.linalg.cholesky_ex(small)
        # S's eigenvalues lie in (0, 1]; the squared smallest Cholesky pivot stands for the smallest
        accurate = (info == 0) & (
            torch.diagonal(factor, dim1=-2, dim2=-1).amin(-1).pow(2) > self.woodbury_min_eigenvalue
        )
        if self.ridge == 0.0:
            accurate = accurate & (count >= self.modes_hat.shape[1])
        chol = torch.where(accurate.reshape(-1, 1, 1), factor, eye)  # the others are solved per signal
        c = torch.cholesky_solve(u @ a0.unsqueeze(-1), chol)  # (B, k, 1)
        alpha = a0 + (wu.transpose(1, 2) @ c).squeeze(-1)
        resid = (centred - F.linear(alpha, self.modes_hat)) * w
        return alpha, (resid.pow(2).sum(-1) / count.clamp(min=1.0)).sqrt(), accurate

    def _solve(
        self, gram: torch.Tensor, rhs: torch.Tensor, centred: torch.Tensor, w: torch.Tensor, count: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """alpha (B, n_m) and residual (B,) from each signal's G (B, n_m, n_m) and right-hand side
        (B, n_m, 1); ``centred`` (B, n_w) samples minus the mean (0 where missing), ``w`` (B, n_w) 1 where
        present, ``count`` (B,) present samples."""
        eye = torch.eye(gram.shape[-1], dtype=gram.dtype, device=gram.device)
        factor, info = torch.linalg.cholesky_ex(gram)
        pivots = torch.diagonal(factor, dim1=-2, dim2=-1)
        # Numerically singular too: squared pivot ratio (~ 1 / cond G) below n_m machine epsilons.
        eps = 2.220446049250313e-16 if gram.dtype == torch.float64 else 1.1920928955078125e-07
        ok = (info == 0) & ((pivots.amin(-1) / pivots.amax(-1)).pow(2) > gram.shape[-1] * eps)
        if self.ridge == 0.0 and not self.bayesian:
            ok = ok & (count >= gram.shape[-1])
        # A signal whose present samples cannot determine the modes gets NaN coefficients and an infinite
        # residual (flagged out of distribution) instead of failing the batch; its system is replaced by
        # the identity so that no NaN reaches the gradients of the others.
        # cholesky_ex: the systems left are positive definite (ok includes the factorisation's info), and it has
        # no error check for a compiled program to call back into Python for (AOTInductor's proxy executor)
        chol = torch.linalg.cholesky_ex(torch.where(ok.reshape(-1, 1, 1), gram, eye))[0]
        alpha = torch.cholesky_solve(rhs, chol).squeeze(-1)
        resid = (centred - F.linear(alpha, self.modes_hat)) * w
        resid = (resid.pow(2).sum(-1) / count.clamp(min=1.0)).sqrt()
        alpha = torch.where(ok.unsqueeze(-1), alpha, torch.full_like(alpha, float("nan")))
        return alpha, torch.where(ok, resid, torch.full_like(resid, float("inf")))

    def reconstruct(self, alpha: torch.Tensor) -> torch.Tensor:
        """The fitted values (B, n_w) at the selected samples."""
        return self.mean_hat + alpha @ self.modes_hat.T

    def condition_number(self) -> float:
        """2-norm condition number of the complete gappy matrix G = V_hat^T R^-1 V_hat + diag(prior precision)
        (V_hat^T V_hat + ridge I for least squares)."""
        v = self.modes_hat.to(torch.float64)
        weighted = torch.linalg.solve(self.noise_covariance.to(torch.float64), v).T if self.bayesian else v.T
        return float(torch.linalg.cond(self._gram(v, weighted, self.prior_precision.to(torch.float64))))

    def extra_repr(self) -> str:
        return f"n_points={self.n_points}, n_modes={self.n_modes}, ridge={self.ridge}, bayesian={self.bayesian}"


@torch.no_grad()
def gappy_statistics(
    snapshots: torch.Tensor,
    modes: torch.Tensor,
    mean: torch.Tensor,
    indices: torch.Tensor,
    noise_std: float = 0.0,
    chunk: int = 2048,
) -> dict[str, torch.Tensor]:
    """The Bayesian gappy layer's statistics from training snapshots.

    Args:
        snapshots: (N, n_e) training records [signal unit].  modes: (n_e, n_m).  mean: (n_e,).
        indices: (n_w,) selected samples.
        noise_std: measurement noise std [signal unit], added as noise_std^2 I to R.

    Returns:
        ``noise_covariance`` (n_w, n_w): covariance over the snapshots of the samples' part that the
        modes leave out, f_hat - y0_hat - V_hat alpha_full (+ noise_std^2 I); ``prior_variance`` (n_m,):
        variance of the full-projection coefficients alpha_full. Float64.
    """
    v = modes.to(torch.float64)
    idx = torch.as_tensor(indices, dtype=torch.long)
    alphas, resids = [], []
    for start in range(0, snapshots.shape[0], chunk):  # the records stay in their dtype; blocks in float64
        c = snapshots[start : start + chunk].to(torch.float64) - mean.to(torch.float64)
        a = c @ v
        alphas.append(a)
        resids.append(c[:, idx] - a @ v[idx].T)
    alpha, resid = torch.cat(alphas), torch.cat(resids)
    cov = torch.cov(resid.T).reshape(idx.numel(), idx.numel())
    cov = cov + noise_std**2 * torch.eye(idx.numel(), dtype=torch.float64)
    return {"noise_covariance": cov, "prior_variance": alpha.var(0)}
