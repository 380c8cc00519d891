"""The online consistency check: can the FDI's own answer reproduce the record? (analysis by synthesis)

:class:`ConsistencyCheck` holds a :class:`~phm_torch.surrogates.forward.ForwardSurrogate` and the POD basis at
the rows it compares: every ``STRIDE``-th sample of a full record (626 of 10,001), or the selected samples
when only those are sent. Its ``forward(x, k_hat, noise)`` returns the statistic
(:func:`~phm_torch.surrogates.forward.consistency_statistic`) over its threshold at the record's noise level,
so > 1 means ``inconsistent``. The thresholds are calibrated by :func:`calibrate_consistency` (phm-evaluate,
on the fdi_band split's records with noise at the interval levels, 1 / 3 / 10 %): a high quantile of the
statistic of the in-distribution records at each level, one row for full records and one for selected
samples, interpolated linearly in the noise level and held at the first and last level (as the k_hat
intervals, :mod:`.fdi_interval`). Uncalibrated (infinite thresholds): never inconsistent.

The noise level of a full record is estimated from it (:func:`~phm_torch.surrogates.augment.noise_level`,
first 1024 samples); selected samples carry none, so unless the caller sends it the largest calibrated level
is assumed: the loosest threshold, no false rejection of a noisy record for want of its level.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Sequence

import torch
from torch import nn

from ..surrogates.augment import add_noise, noise_level, rms
from ..surrogates.forward import ForwardSurrogate, consistency_statistic
from ..surrogates.full_signal_check import record_stride
from .noise_threshold import conformal_quantile, interpolate_levels

NOISE_WINDOW = 1024
# 0.997, not 0.995: each check of a record flags its own share of clean ones and the shares add up; at 0.995
# this check alone flagged 0.6 % of 8,000 fresh val records, all checks together 0.9-1.6 % (budget: 1 %)
DEFAULT_QUANTILE = 0.997


class ConsistencyCheck(nn.Module):
    """Statistic of full records or selected samples against the forward surrogate's prediction at k_hat.

    Args:
        model: fitted forward surrogate (floors set, :func:`~phm_torch.surrogates.forward.fit_forward_check`).
        mean: (n_e,) POD mean [A].  modes: (n_e, n_m) POD modes.  indices: (n_w,) selected samples.
        thresholds: (2, n_levels) statistic thresholds, row 0 full records, row 1 selected samples; None: inf.
        noise_levels: (n_levels,) increasing relative noise levels of the threshold columns; None: one level, 0.
    """

    def __init__(
        self,
        model: ForwardSurrogate,
        mean: torch.Tensor,
        modes: torch.Tensor,
        indices: torch.Tensor,
        thresholds: torch.Tensor | None = None,
        noise_levels: torch.Tensor | None = None,
    ):
        super().__init__()
        dtype = modes.dtype
        self.model = model
        stride = record_stride(int(mean.shape[0]), int(modes.shape[1]))
        rows = torch.arange(0, mean.shape[0], stride)
        idx = torch.as_tensor(indices, dtype=torch.long)
        self.register_buffer("rows", rows)
        self.register_buffer("indices", idx)
        self.register_buffer("mean_rows", mean[rows].clone())
        self.register_buffer("modes_rows", modes[rows].clone().contiguous())
        self.register_buffer("mean_hat", mean[idx].clone())
        self.register_buffer("modes_hat", modes[idx].clone().contiguous())
        self.register_buffer("floors", torch.stack([model.floor_full_, model.floor_samples_]).to(dtype))
        self.n_full, self.n_points = int(mean.shape[0]), int(idx.numel())
        self.stride = stride
        self.noise_window = NOISE_WINDOW
        self.set_thresholds(thresholds, noise_levels)

    def set_thresholds(self, thresholds: torch.Tensor | None, noise_levels: torch.Tensor | None) -> None:
        """Set the (2, n_levels) thresholds at the increasing ``noise_levels`` (n_levels,) (None: uncalibrated)."""
        dtype = self.modes_rows.dtype
        t = (
            torch.full((2, 1), math.inf, dtype=dtype)
            if thresholds is None
            else torch.as_tensor(thresholds, dtype=dtype)
        )
        levels = (
            torch.zeros(t.shape[-1], dtype=dtype)
            if noise_levels is None
            else torch.as_tensor(noise_levels, dtype=dtype).reshape(-1)
        )
        if (
            t.dim() != 2
            or t.shape[0] != 2
            or levels.numel() != t.shape[1]
            or bool((levels[1:] <= levels[:-1]).any())
            or not bool((t > 0).all())
        ):
            raise ValueError(
                f"consistency: thresholds must be (2, n_levels) > 0 at n_levels increasing noise levels, "
                f"got {tuple(t.shape)} at {levels.tolist()}"
            )
        self.register_buffer("thresholds", t.contiguous())
        self.register_buffer("noise_levels", levels)

    def statistic(self, x: torch.Tensor, k_hat: torch.Tensor, noise: torch.Tensor) -> torch.Tensor:
        """Statistic (B,) of full records (B, n_full) or selected samples (B, n_points) [A] at the FDI's
        estimates k_hat (B, 8), the records' relative noise (B,) given."""
        if x.shape[1] == self.n_full:
            # a strided slice, not index_select on dim 1: the same rows (arange(0, n, STRIDE)) at ~2/3 of the cost
            return self.rows_statistic(x[:, :: self.stride], k_hat, noise)
        return consistency_statistic(
            x.to(self.mean_hat.dtype), self.mean_hat, self.modes_hat, self.model(k_hat), noise, self.floors[1]
        )

    def rows_statistic(self, y: torch.Tensor, k_hat: torch.Tensor, noise: torch.Tensor) -> torch.Tensor:
        """The full-record statistic (B,) from the records' samples at ``rows`` (B, n_full / STRIDE) [A], gathered
        by the caller (:class:`~phm_torch.online.step.OnlineStep` reads each record once for every check)."""
        y = y.to(self.mean_rows.dtype)
        return consistency_statistic(y, self.mean_rows, self.modes_rows, self.model(k_hat), noise, self.floors[0])

    def threshold(self, noise: torch.Tensor, full: bool) -> torch.Tensor:
        """Threshold (B,) at relative noise levels (B,), linear between the calibrated levels."""
        return interpolate_levels(self.noise_levels, self.thresholds[0 if full else 1], noise)

    def record_noise(self, x: torch.Tensor, noise: torch.Tensor | None) -> torch.Tensor:
        """The records' relative noise (B,): ``noise`` when given, else estimated from a full record, else (selected
        samples) the largest calibrated level."""
        if noise is not None:
            return noise.to(self.mean_rows.dtype)
        if x.shape[1] == self.n_full:
            return noise_level(x.to(self.mean_rows.dtype), self.noise_window)
        return self.noise_levels[-1].expand(x.shape[0])

    def forward(self, x: torch.Tensor, k_hat: torch.Tensor, noise: torch.Tensor | None = None) -> torch.Tensor:
        """Statistic over threshold (B,): > 1 ``inconsistent`` (0 where uncalibrated, NaN with no finite sample)."""
        level = self.record_noise(x, noise)
        return self.statistic(x, k_hat, level) / self.threshold(level, x.shape[1] == self.n_full)


@torch.no_grad()
def consistency_statistics(
    pipeline: nn.Module, x: torch.Tensor, block_rows: int = 1024
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """For full records x (N, n_full) [A]: the full-record statistic (N,), the selected-sample statistic (N,) (the
    record's estimated noise told), that noise (N,) and the pipeline's OOD flag (N,) bool, in row blocks."""
    check: ConsistencyCheck = pipeline.consistency_check
    out: list[list[torch.Tensor]] = [[], [], [], []]
    for block in x.split(block_rows):
        block = block.to(pipeline.times.dtype)
        k_hat, _, _, ood, _ = pipeline(block)
        level = check.record_noise(block, None)
        samples = block.index_select(1, check.indices)
        for store, value in zip(
            out, (check.statistic(block, k_hat, level), check.statistic(samples, k_hat, level), level, ood)
        ):
            store.append(value)
    return tuple(torch.cat(v) for v in out)  # type: ignore[return-value]


def calibrate_consistency(
    pipeline: nn.Module, clean: torch.Tensor, levels: Sequence[float], seed: int, quantile: float = DEFAULT_QUANTILE
) -> dict[str, list]:
    """Calibrate the pipeline's consistency thresholds in place on held-out noise-free records.

    Args:
        pipeline: an :class:`~phm_torch.online.OnlinePipeline` with a consistency check (``has_consistency``).
        clean: (N, n_full) noise-free held-out records [A] (phm-evaluate's fdi_band split).
        levels: increasing relative noise levels; white noise of each level is added to the records.
        seed: seeds the noise.   quantile: the quantile of the in-distribution records' statistic taken at each
            level (split-conformal: the ceil((n + 1) q)-th smallest).

    Returns: ``{"thresholds": [[full...], [samples...]], "noise_levels": [...], "quantile": q}`` (the JSON of
    rul_calibration.json's ``consistency``; phm-export passes it back to :meth:`OnlinePipeline.from_bundle`).
    """
    if not 0.0 < quantile < 1.0:
        raise ValueError(f"consistency.quantile must be in (0, 1), got {quantile!r}")
    if not levels or any(b <= a for a, b in itertools.pairwise(levels)):
        raise ValueError(f"consistency: noise levels must be increasing, got {list(levels)}")
    pipeline.consistency_check.set_thresholds(None, None)  # statistics unflagged by the check itself
    rows: list[list[float]] = [[], []]
    for i, level in enumerate(levels):
        noisy = (
            add_noise(clean, rms(clean), level, torch.Generator().manual_seed(seed + 20 + i)) if level > 0 else clean
        )
        full, samples, _, ood = consistency_statistics(pipeline, noisy)
        keep = ~ood
        if int(keep.sum()) < 1:
            raise ValueError(f"consistency: no in-distribution calibration record at noise {level}")
        for row, stat in zip(rows, (full[keep], samples[keep])):
            row.append(conformal_quantile(stat, quantile))
    out = {"thresholds": rows, "noise_levels": [float(v) for v in levels], "quantile": float(quantile)}
    pipeline.consistency_check.set_thresholds(torch.tensor(rows), torch.tensor(out["noise_levels"]))
    return out


@torch.no_grad()
def flag_rates(pipeline: nn.Module, x: torch.Tensor, seed: int, levels: Sequence[float] = (0.0, 0.01, 0.03)) -> dict:
    """Per relative noise level (white noise added to the full records x (N, n_full) [A]): the share flagged by the
    consistency check alone (``inconsistent``) and by any check (``flagged``)."""
    out = {}
    for i, level in enumerate(levels):
        noisy = add_noise(x, rms(x), level, torch.Generator().manual_seed(seed + i)) if level > 0 else x
        full, _, noise, ood = consistency_statistics(pipeline, noisy)
        inconsistent = full > pipeline.consistency_check.threshold(noise, True)
        out[f"{level:g}"] = {"inconsistent": float(inconsistent.double().mean()), "flagged": float(ood.double().mean())}
    return out


def recalibrate_consistency(
    pipeline: nn.Module, records: torch.Tensor, quantile: float, seed: int, calibrate_records: int
) -> dict[str, dict]:
    """Move the consistency check's thresholds to another ``quantile``, in place, at the noise levels it has.

    Args:
        pipeline: an :class:`~phm_torch.online.OnlinePipeline` with a consistency check.
        records: (N, n_full) noise-free held-out records [A]; the first ``calibrate_records`` calibrate, the rest
            measure the flagged shares before and after (at least 10 of them).

    Returns: ``{"before": {"flag_rates"}, "after": {"calibration", "flag_rates"}}``.
    """
    if not getattr(pipeline, "has_consistency", False):
        raise ValueError("recalibrate_consistency: the pipeline has no consistency check")
    if not 0 < calibrate_records <= records.shape[0] - 10:
        raise ValueError(
            f"calibrate_records must be in [1, {records.shape[0] - 10}] (10 of the {records.shape[0]} records left "
            f"to check the result on), got {calibrate_records!r}"
        )
    x_cal, x_check = records[:calibrate_records], records[calibrate_records:]
    before = flag_rates(pipeline, x_check, seed + 1)
    levels = [float(v) for v in pipeline.consistency_check.noise_levels.tolist()]
    calibration = calibrate_consistency(pipeline, x_cal, levels, seed, quantile)
    return {
        "before": {"flag_rates": before},
        "after": {"calibration": calibration, "flag_rates": flag_rates(pipeline, x_check, seed + 1)},
    }
