"""Q-DEIM: the pivots of a column-pivoted QR of the transposed mode matrix.

This is exactly PySensors' ``QR`` optimizer (``scipy.linalg.qr(basis.T, pivoting=True)``, pivots taken
in order): the first n_m pivots make V[S] as well conditioned as the greedy pivoting can
(Drmac & Gugercin 2016). Pivots past the n_m-th are LAPACK's order of the columns left after the
rank is exhausted, carrying no information; use the ``greedy`` selector to oversample.
"""

from __future__ import annotations

import numpy as np
import scipy.linalg
import torch

from .base import Selector


def qr_pivots(modes: torch.Tensor) -> np.ndarray:
    """Full pivot order (n_e,) of the column-pivoted QR of modes^T (n_m, n_e), as PySensors ranks sensors."""
    _, _, piv = scipy.linalg.qr(modes.detach().cpu().numpy().T, pivoting=True, mode="economic")
    return piv


class QDEIMSelector(Selector):
    """The first ``n_points`` pivots of the pivoted QR of the modes (PySensors ``QR``).

    Args:
        n_points: number of samples to keep (informative up to n_m; see the module note).
    """

    name = "qdeim"

    def _select(self, modes: torch.Tensor, time: torch.Tensor) -> torch.Tensor:
        return torch.from_numpy(qr_pivots(modes)[: self.n_points].copy())
