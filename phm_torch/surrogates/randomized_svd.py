"""Randomized SVD of centred snapshots, streamed over row blocks (Halko, Martinsson & Tropp, alg. 5.1).

The POD of a large store needs the leading right singular vectors of Y - 1 y0^T, with Y (n_s, n_e)
float32 in memory. ``torch.svd_lowrank`` needs that centred matrix (or a float64 copy of Y) whole: 6.4 GB
at 80,000 x 10,001. Here every product with the centred matrix is summed over row blocks of Y, each
cast to float64 and centred on its own, so the extra memory is one block plus the (n_s + n_e, q) bases.
The random test matrix and the sequence of QR steps are those of ``torch.svd_lowrank`` (same seed, same
draw), so the two agree to float64 round-off.
"""

from __future__ import annotations

import torch

F64 = torch.float64


def _centred_blocks(y: torch.Tensor, mean: torch.Tensor, block_rows: int):
    for start in range(0, y.shape[0], block_rows):
        block = y[start : start + block_rows].to(F64, copy=True)
        block -= mean
        yield start, block


def centred_mean_and_energy(y: torch.Tensor, block_rows: int) -> tuple[torch.Tensor, float]:
    """Mean signal (n_e,) float64 and the squared Frobenius norm of Y - 1 y0^T, both over row blocks."""
    total = torch.zeros(y.shape[1], dtype=F64)
    for start in range(0, y.shape[0], block_rows):
        total += y[start : start + block_rows].to(F64).sum(0)
    mean = total / y.shape[0]
    energy = sum(float(torch.linalg.vector_norm(b)) ** 2 for _, b in _centred_blocks(y, mean, block_rows))
    return mean, energy


def randomized_svd_centred(
    y: torch.Tensor, mean: torch.Tensor, q: int, n_iter: int, block_rows: int = 2048
) -> tuple[torch.Tensor, torch.Tensor]:
    """Leading ``q`` singular values and right singular vectors of Y - 1 y0^T, streamed.

    Args:
        y: (n_s, n_e) snapshots, any floating dtype (left untouched).
        mean: (n_e,) float64 mean signal y0.
        q: number of singular triplets (the sketch size; callers add oversampling).
        n_iter: power iterations (each is two passes over Y).
        block_rows: rows of Y cast to float64 at a time.

    Returns:
        s (q,) float64 singular values, descending; v (n_e, q) float64 right singular vectors.
        The caller seeds the RNG (one ``torch.randn`` draw, as ``torch.svd_lowrank``).
    """
    n_s, n_e = y.shape

    def times(x: torch.Tensor) -> torch.Tensor:  # (Y - 1 y0^T) x, x (n_e, q) -> (n_s, q)
        out = torch.empty(n_s, x.shape[1], dtype=F64)
        for start, block in _centred_blocks(y, mean, block_rows):
            out[start : start + block.shape[0]] = block @ x
        return out

    def times_t(z: torch.Tensor) -> torch.Tensor:  # (Y - 1 y0^T)^T z, z (n_s, q) -> (n_e, q)
        out = torch.zeros(n_e, z.shape[1], dtype=F64)
        for start, block in _centred_blocks(y, mean, block_rows):
            out += block.T @ z[start : start + block.shape[0]]
        return out

    # torch.svd_lowrank works on the tall orientation: A = Yc when n_s >= n_e, A = Yc^T otherwise
    tall = n_s >= n_e
    a, a_t = (times, times_t) if tall else (times_t, times)
    basis = torch.linalg.qr(a(torch.randn(n_e if tall else n_s, q, dtype=F64))).Q
    for _ in range(n_iter):
        basis = torch.linalg.qr(a_t(basis)).Q
        basis = torch.linalg.qr(a(basis)).Q
    b = a_t(basis).T  # Q^T A: (q, n) with n the short side
    u, s, vh = torch.linalg.svd(b, full_matrices=False)
    v = vh.T if tall else basis @ u
    return s, v
