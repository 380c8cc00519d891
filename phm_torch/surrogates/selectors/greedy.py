"""Greedy oversampling for gappy POD (n_points > n_modes): GappyPOD+E and GappyPOD+D.

Start from the Q-DEIM points (the first min(n_points, n_m) QR pivots), then add one sample at a time:

* ``e_optimal``: the sample that most raises the smallest eigenvalue of the gappy matrix
  G = V[S]^T V[S] (the square of the smallest singular value of V[S]), which bounds the amplification
  of noise in the least-squares coefficients (Peherstorfer, Drmac & Gugercin 2020);
* ``d_optimal``: the sample that most raises det(G); by the matrix determinant lemma that is the one
  maximising v^T G^-1 v (its leverage), in closed form.

Below n_m points the selection is Q-DEIM's.
"""

from __future__ import annotations

import torch

from .base import Selector
from .qdeim import qr_pivots

CRITERIA = ("e_optimal", "d_optimal")


class GreedySelector(Selector):
    """Q-DEIM start plus greedy E- or D-optimal oversampling.

    Args:
        n_points: number of samples to keep.
        criterion: ``e_optimal`` (raise the smallest eigenvalue of G) or ``d_optimal`` (raise det G).
        chunk: candidates evaluated per batched eigenvalue call (memory: chunk * n_m^2 floats).
    """

    name = "greedy"

    def __init__(self, n_points: int, criterion: str = "e_optimal", chunk: int = 2048):
        super().__init__(n_points)
        if criterion not in CRITERIA:
            raise ValueError(f"selector.criterion must be one of {list(CRITERIA)}, got {criterion!r}")
        self.criterion = criterion
        self.chunk = chunk

    def _select(self, modes: torch.Tensor, time: torch.Tensor) -> torch.Tensor:
        n_e, n_m = modes.shape
        start = min(self.n_points, n_m)
        chosen = [int(i) for i in qr_pivots(modes)[:start]]
        free = torch.ones(n_e, dtype=torch.bool)
        free[chosen] = False
        gram = modes[chosen].T @ modes[chosen]
        for _ in range(self.n_points - start):
            score = self._scores(modes, gram)
            score[~free] = -torch.inf
            best = int(torch.argmax(score))
            chosen.append(best)
            free[best] = False
            gram = gram + torch.outer(modes[best], modes[best])
        return torch.tensor(chosen)

    def _scores(self, modes: torch.Tensor, gram: torch.Tensor) -> torch.Tensor:
        """(n_e,) value of the criterion after adding each sample."""
        if self.criterion == "d_optimal":
            sol = torch.linalg.solve(gram, modes.T)  # G^-1 v for every candidate, (n_m, n_e)
            return (modes.T * sol).sum(0)
        out = []
        for rows in modes.split(self.chunk):
            updated = gram + rows.unsqueeze(-1) * rows.unsqueeze(-2)  # (c, n_m, n_m)
            out.append(torch.linalg.eigvalsh(updated)[:, 0])
        return torch.cat(out)

    def get_params(self) -> dict[str, object]:
        return {**super().get_params(), "criterion": self.criterion, "chunk": self.chunk}
