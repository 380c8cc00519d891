"""Proper orthogonal decomposition (POD) as a frozen linear layer.

A snapshot matrix Y (n_s, n_e) of signals (one per row, n_e samples each) is centred on its mean
signal y0 and decomposed by a thin SVD, Y - y0 = U S V^T. The first ``n_modes`` right singular vectors
are the POD modes v_i (columns of ``modes_``, orthonormal, (n_e, n_m)); the POD coefficients of a
signal are alpha = (y - y0) V, and y ~ y0 + alpha V^T (seed paper, eq. 4). The energy fraction of
mode i is s_i^2 / ||Y - y0||_F^2.

The paper centres on the nominal signal; here y0 is the mean of the training snapshots, which makes the
modes the principal directions (the variance, not the offset from nominal, is what they capture).
"""

from __future__ import annotations

import torch
from torch import nn

from .randomized_svd import centred_mean_and_energy, randomized_svd_centred

SOLVERS = ("auto", "snapshots", "full", "randomized")
# "auto" takes the method of snapshots up to this many snapshots, the randomized SVD above.
AUTO_SNAPSHOT_LIMIT = 1000


class POD(nn.Module):
    """Frozen POD layer: ``forward(y) -> alpha``, ``reconstruct(alpha) -> y``.

    Args:
        n_modes: number of retained modes n_m (paper: 22).
        solver: ``snapshots`` (Sirovich's method of snapshots: ``eigh`` of the (n_s, n_s) Gram matrix,
            exact to float64 precision for the modes that matter, n_s^2 n_e work), ``full``
            (``torch.linalg.svd`` of the (n_s, n_e) matrix, slower), ``randomized``
            (the algorithm of ``torch.svd_lowrank`` with 20 extra vectors and ``n_iter`` power
            iterations, streamed over row blocks so that no float64 copy of the snapshots is made: 3x
            faster than snapshots at n_s = 2000 with modes matching to 1e-4) or ``auto`` (snapshots up
            to 1000 snapshots, randomized above). ``snapshots`` and ``full`` hold one float64 copy.
        n_spectrum: number of leading singular values kept for the energy spectrum (at least
            ``n_modes``; ``None`` = max(n_modes, 100)).
        n_iter: power iterations of the randomized solver.
        seed: seed of the randomized solver's test matrix.
        block_rows: snapshot rows cast to float64 at a time by the randomized solver (memory: one block
            of block_rows x n_e float64, 160 MB at the default and 10,001 samples).

    Fitted buffers:
        mean_: (n_e,) mean training signal y0 [signal unit, A for currents].
        modes_: (n_e, n_m) orthonormal modes, each signed so that its largest-magnitude entry is > 0.
        singular_values_: (n_spec,) leading singular values of Y - y0 [A].
        energy_: (n_spec,) energy fraction of each mode, s_i^2 / ||Y - y0||_F^2 (fractions).
    """

    def __init__(
        self,
        n_modes: int,
        solver: str = "auto",
        n_spectrum: int | None = None,
        n_iter: int = 6,
        seed: int = 0,
        block_rows: int = 2048,
    ):
        super().__init__()
        if isinstance(n_modes, bool) or not isinstance(n_modes, int) or n_modes < 1:
            raise ValueError(f"n_modes must be a positive integer, got {n_modes!r}")
        if solver not in SOLVERS:
            raise ValueError(f"pod.solver must be one of {list(SOLVERS)}, got {solver!r}")
        if n_spectrum is not None and (not isinstance(n_spectrum, int) or n_spectrum < n_modes):
            raise ValueError(f"pod.n_spectrum must be an integer >= n_modes ({n_modes}), got {n_spectrum!r}")
        if isinstance(block_rows, bool) or not isinstance(block_rows, int) or block_rows < 1:
            raise ValueError(f"pod.block_rows must be a positive integer, got {block_rows!r}")
        self.n_modes = n_modes
        self.block_rows = block_rows
        self.solver = solver
        self.n_spectrum = n_spectrum
        self.n_iter = n_iter
        self.seed = seed
        self.register_buffer("mean_", torch.empty(0))
        self.register_buffer("modes_", torch.empty(0, n_modes))
        self.register_buffer("singular_values_", torch.empty(0))
        self.register_buffer("energy_", torch.empty(0))

    @property
    def fitted(self) -> bool:
        return self.mean_.numel() > 0

    def fit(self, snapshots: torch.Tensor) -> POD:
        """Fit the modes to snapshots (n_s, n_e), one signal per row; returns self.

        The SVD runs in float64; the buffers take the snapshots' floating dtype.
        """
        if snapshots.ndim != 2:
            raise ValueError(f"snapshots must be (n_s, n_e), got shape {tuple(snapshots.shape)}")
        n_s, n_e = snapshots.shape
        if n_s < 2:
            raise ValueError(f"POD needs at least 2 snapshots, got {n_s}")
        for start in range(0, n_s, self.block_rows):
            if not torch.isfinite(snapshots[start : start + self.block_rows]).all():
                raise ValueError("snapshots contain NaN or inf")
        max_modes = min(n_s - 1, n_e)  # centring removes one dimension
        if self.n_modes > max_modes:
            raise ValueError(
                f"n_modes={self.n_modes} exceeds the rank of {n_s} centred snapshots of "
                f"{n_e} samples (at most {max_modes})"
            )
        dtype = snapshots.dtype if snapshots.is_floating_point() else torch.float32
        n_spec = min(self.n_spectrum or max(self.n_modes, 100), max_modes)
        solver = self.solver
        if solver == "auto":
            solver = "snapshots" if n_s <= AUTO_SNAPSHOT_LIMIT else "randomized"
        if solver == "randomized":  # streamed over row blocks: no float64 copy of the snapshots
            mean, total = centred_mean_and_energy(snapshots, self.block_rows)
            with torch.random.fork_rng(devices=[]):
                torch.manual_seed(self.seed)
                s, v = randomized_svd_centred(
                    snapshots, mean, min(n_spec + 20, max_modes), self.n_iter, self.block_rows
                )
            v, s = v[:, :n_spec], s[:n_spec]
        else:
            yc = snapshots.to(torch.float64, copy=True)  # one float64 copy, centred in place
            mean = yc.mean(0)
            yc -= mean
            total = float(torch.linalg.vector_norm(yc)) ** 2
            if solver == "snapshots":
                evals, u = torch.linalg.eigh(yc @ yc.T)  # ascending
                evals, u = evals.flip(0)[:n_spec], u.flip(1)[:, :n_spec]
                s = evals.clamp(min=0.0).sqrt()
                v = (yc.T @ u) / s.clamp(min=torch.finfo(torch.float64).tiny)
            else:
                _, s, vh = torch.linalg.svd(yc, full_matrices=False)
                v = vh[:n_spec].T
                s = s[:n_spec]
        modes = v[:, : self.n_modes]
        flip = torch.sign(modes.gather(0, modes.abs().argmax(0, keepdim=True)))
        modes = modes * flip
        self.mean_ = mean.to(dtype)
        self.modes_ = modes.to(dtype).contiguous()
        self.singular_values_ = s.to(dtype)
        self.energy_ = (s.pow(2) / max(total, torch.finfo(torch.float64).tiny)).to(dtype)
        return self

    def _check(self, x: torch.Tensor, name: str) -> None:
        if not self.fitted:
            raise ValueError("POD is not fitted: call fit(snapshots) first")
        if x.shape[-1] != self.mean_.shape[0]:
            raise ValueError(
                f"{name} must have {self.mean_.shape[0]} samples in the last axis, got shape {list(x.shape)}"
            )

    def forward(self, signals: torch.Tensor) -> torch.Tensor:
        """POD coefficients alpha (..., n_m) of full signals (..., n_e) (orthogonal projection)."""
        self._check(signals, "signals")
        return (signals - self.mean_) @ self.modes_

    def reconstruct(self, alpha: torch.Tensor) -> torch.Tensor:
        """Signals (..., n_e) from coefficients (..., n_m): y0 + alpha V^T."""
        if alpha.shape[-1] != self.n_modes:
            raise ValueError(f"alpha must have {self.n_modes} coefficients, got shape {tuple(alpha.shape)}")
        return self.mean_ + alpha @ self.modes_.T

    def cumulative_energy(self) -> torch.Tensor:
        """(n_spec,) retained energy fraction with the first 1, 2, ... modes (the paper's eigenvalue sum)."""
        return self.energy_.cumsum(0)

    def truncated(self, n_modes: int) -> POD:
        """A copy that keeps only the first ``n_modes`` modes (same spectrum), for mode-count sweeps."""
        if not 1 <= n_modes <= self.n_modes:
            raise ValueError(f"n_modes must be in [1, {self.n_modes}], got {n_modes}")
        out = POD(
            n_modes,
            self.solver,
            self.n_spectrum and max(self.n_spectrum, n_modes),
            self.n_iter,
            self.seed,
            self.block_rows,
        )
        out.mean_, out.modes_ = self.mean_.clone(), self.modes_[:, :n_modes].clone()
        out.singular_values_, out.energy_ = self.singular_values_.clone(), self.energy_.clone()
        return out

    def extra_repr(self) -> str:
        return f"n_modes={self.n_modes}, n_samples={self.mean_.numel()}"
