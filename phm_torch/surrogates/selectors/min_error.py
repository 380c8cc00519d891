"""Data-driven greedy oversampling: add the sample that most lowers the gappy coefficient error of the
training signals themselves.

For training signals y_s (centred) with full coefficients a_s = V^T y_s and out-of-span residuals
r_s = y_s - V a_s, gappy POD on the samples S recovers a_s + e_s with e_s = G_S^-1 V_S^T r_s[S]: the
error is the residual aliased through the selected rows. Starting from the Q-DEIM points (the first
n_m QR pivots), each step adds the sample j minimising sum_s w_s ||e_s||^2, with w_s the err_alpha
normalisation 1 / (max a_s - min a_s)^2. Adding row v_j changes e_s, by Sherman-Morrison, to
e_s + u_j (r_sj - v_j^T e_s) / (1 + v_j^T u_j) with u_j = G_S^-1 v_j, so every candidate is scored in
one batched expression (n_e x n_signals x n_m work per step).

Unlike the E/D-optimal criteria, which see only the modes, this one sees what the modes leave out (for
the HF envelope current, PWM-like ripple) and places the points where it averages out. It needs the
training snapshots: ``fit(modes, time, snapshots=Y)``.
"""

from __future__ import annotations

import torch

from .base import Selector, check_count
from .qdeim import qr_pivots


class MinErrorSelector(Selector):
    """Q-DEIM start plus greedy minimisation of the training gappy coefficient error.

    Args:
        n_points: number of samples to keep (>= n_m for the greedy part to run).
        n_signals: training signals used for the error (the first ones of the snapshots).
    """

    name = "min_error"
    needs_snapshots = True

    def __init__(self, n_points: int, n_signals: int = 1000):
        super().__init__(n_points)
        self.n_signals = check_count(n_signals, "selector.n_signals")

    def _select(self, modes: torch.Tensor, time: torch.Tensor) -> torch.Tensor:
        n_e, n_m = modes.shape
        chosen = [int(i) for i in qr_pivots(modes)[: min(self.n_points, n_m)]]
        if self.n_points <= n_m:
            return torch.tensor(chosen)
        snap = self._snapshots
        centred = snap - snap.mean(0) if self._mean is None else snap - self._mean
        coef = centred @ modes  # (n_sig, n_m)
        resid = (centred - coef @ modes.T).T.contiguous()  # (n_e, n_sig)
        weight = 1.0 / (coef.amax(1) - coef.amin(1)).clamp(min=torch.finfo(coef.dtype).tiny) ** 2
        free = torch.ones(n_e, dtype=torch.bool)
        free[chosen] = False
        for _ in range(self.n_points - len(chosen)):
            rows = modes[chosen]
            ginv = torch.linalg.inv(rows.T @ rows)
            err = ginv @ (rows.T @ resid[chosen])  # (n_m, n_sig) current errors
            u = ginv @ modes.T  # (n_m, n_e)
            denom = 1.0 + (modes.T * u).sum(0)  # (n_e,)
            step = (resid - modes @ err) / denom.unsqueeze(-1)  # (n_e, n_sig)
            cross = u.T @ err  # (n_e, n_sig)
            change = 2.0 * (step * cross) @ weight + u.pow(2).sum(0) * (step.pow(2) @ weight)
            change[~free] = torch.inf
            best = int(torch.argmin(change))
            chosen.append(best)
            free[best] = False
        return torch.tensor(chosen)

    def fit(
        self,
        modes: torch.Tensor,
        time: torch.Tensor | None = None,
        snapshots: torch.Tensor | None = None,
        mean: torch.Tensor | None = None,
    ) -> MinErrorSelector:
        """As :meth:`Selector.fit`, with the training snapshots (n_s, n_e) [A] and optionally the POD mean
        signal (n_e,) (default: the snapshots' mean)."""
        if snapshots is None:
            raise ValueError("selector min_error needs the training snapshots: fit(modes, time, snapshots=Y)")
        if snapshots.ndim != 2 or snapshots.shape[1] != modes.shape[0]:
            raise ValueError(f"snapshots must be (n_s, {modes.shape[0]}), got {tuple(snapshots.shape)}")
        self._snapshots = snapshots[: self.n_signals].detach().to(torch.float64).cpu()  # only these are used
        self._mean = None if mean is None else mean.detach().to(torch.float64).cpu()
        try:
            return super().fit(modes, time)
        finally:
            del self._snapshots, self._mean

    def get_params(self) -> dict[str, object]:
        return {**super().get_params(), "n_signals": self.n_signals}
