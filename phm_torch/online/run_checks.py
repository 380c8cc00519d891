"""Checks on the runs of a full record's samples: ``gap``, ``stuck`` and ``held`` (:func:`run_reasons`).

The reasons are described with the input contract (:mod:`phm_torch.online.input_contract`), which applies them to
a full record as measured.
"""

from __future__ import annotations

import torch

STUCK_RUN = 0.005  # of the record (50 samples, 2.5 ms of the chirp): 12 x the longest run of a clean HF record
STUCK_MIN = 12  # samples, on a short or slowly sampled record (0.005 of 501 samples is 2.5): 3 x that longest run
MOVING_SHARE = 0.01  # ... in a record whose other neighbours are equal at most this often (noisy data: ~0)
HELD_SHARE = 0.4  # held data: equal neighbours (held x2: 50 %)...
HELD_ALIGNED = 0.9  # ... and this share of its changes on one residue of a period k (quantised data: ~1 / k)
HELD_MAX_PERIOD = 64
HELD_MIN_CHANGES = 10


def run_reasons(current: torch.Tensor) -> list[str]:
    """``gap``, ``stuck`` and ``held`` (module docstring) of a current record (n,) [A]; a missing (NaN) sample ends
    a run of equal samples.

    A record that repeats values everywhere (noise-free data written at a CSV's resolution, a coarse ADC) is
    neither: its long runs are its resolution, and its changes fall anywhere, not on every k-th sample."""
    x = current.double()
    same = x[1:] == x[:-1]  # NaN compares unequal
    pairs = same.numel()
    if pairs < 2:
        return []
    change = torch.nonzero(~same).flatten()  # x[i + 1] != x[i]
    edges = torch.cat([torch.tensor([-1]), change, torch.tensor([pairs])])
    lengths = edges[1:] - edges[:-1] - 1  # runs of equal neighbours between changes; the first one is leading
    longest = int(lengths[1:].max()) if lengths.numel() > 1 else 0
    repeats = int(same.sum())
    reasons = []
    limit = max(STUCK_RUN * x.numel(), STUCK_MIN)  # samples of a stuck run or a gap
    missing = (~torch.isfinite(x)).to(torch.int64)
    if bool(missing.any()):  # the longest gap: the running count of missing samples, reset at every present one
        filled = torch.cumsum(missing, 0)
        gap = filled - torch.cummax(torch.where(missing == 0, filled, torch.zeros_like(filled)), 0).values
        if int(gap.max()) >= limit:
            reasons.append("gap")
    moving = (repeats - longest) <= MOVING_SHARE * max(1, pairs - longest)  # the rest of the record moves
    if longest + 1 >= limit and moving:  # a run of m equal neighbours holds m + 1 samples
        reasons.append("stuck")
    if repeats >= HELD_SHARE * pairs and change.numel() >= HELD_MIN_CHANGES:
        starts = change + 1  # where a new value starts: every k-th sample for data held k times
        for k in range(2, HELD_MAX_PERIOD + 1):
            if int(torch.bincount(starts % k, minlength=k).max()) >= HELD_ALIGNED * change.numel():
                reasons.append("held")
                break
    return reasons
