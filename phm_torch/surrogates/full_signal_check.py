"""Out-of-distribution check on a full record: three statistics a few gappy samples cannot see.

With n_points close to n_modes (the paper: 30 and 22) the gappy residual has few degrees of freedom and
heavy-fault training records (ringing phase currents, several amperes of residual) overlap garbage.
A full record says much more:

* **POD residual** - the share of the record the basis cannot explain,
  ``r(y) = || d - P P^T d || / || d ||`` with ``d = y - mean``: ~1 for strong noise or a foreign waveform.
  It is computed on every ``stride``-th sample (default 16: 626 of 10001, ~5 us per record in a batch)
  with an orthonormalised basis of those rows. Its threshold is a training quantile (``phm-train``).
  The first mode is nearly the mean record, so a smooth record of the right size (a sine, a clipped
  record, weak noise around zero) stays close to the span; hence the two shape statistics below.
* **roughness** - RMS of the sample-to-sample difference over the RMS about the record's mean: sqrt(2)
  for white noise, 0.02 (median) to 0.6 (max) over the paper-scale training set, whose envelope current
  is smooth at 20 kHz. Above 1 the noise is comparable to the signal itself.
* **plateau** - the fraction of samples within ``plateau_tolerance`` of the record's range from its
  maximum: at most 0.2 % over the paper-scale training set (a peak lasts a few samples), 0.6-30 % for a
  record clipped at 50-80 % of its peak (ADC or probe saturation), 2.4 % for a sine's slow crests.

All three use every ``stride``-th sample (the shape statistics at a jittered stride, against aliasing;
the roughness with each sample's right neighbour): a full pass over every sample costs as much as the
rest of the online step in a batch.

The two shape thresholds are physical defaults, not training quantiles: a measurement from another
bench (more ripple, ADC quantisation) should not be rejected for differing from this simulator in
detail, only for not looking like an envelope current at all. They are only ever raised: the plateau's
to three sampled points on a short record, and both by ``phm-train`` above the clean training records'
own (:func:`~.ood_calibration.shape_thresholds`) where the actuator's sampling makes them reach it: a
test command ending on a slow crest (a 10 Hz chirp's last crest sampled at 10 kHz puts 2-3 of 313 points
within the tolerance of the maximum: 9 % of a clean training set was called clipped), a sample rate a few
times the filter's cutoff (roughness grows as the rate falls).
"""

from __future__ import annotations

import torch
from torch import nn

STRIDE = 16  # every 16th sample of a full record: 626 of 10,001 ...
ROWS_PER_MODE = 8  # ... or fewer on a short record, so that the rows outnumber the POD modes this many times
DEFAULT_ROUGHNESS_THRESHOLD = 1.0
DEFAULT_PLATEAU_THRESHOLD = 0.005
# a record's maximum is always on its plateau, and a slow crest puts a second sampled point within the
# tolerance of it: a plateau needs a third (on a short record 0.5 % is fewer than one sampled point)
PLATEAU_MIN_POINTS = 2.5


def record_stride(n_samples: int, n_modes: int) -> int:
    """The stride of the rows the full-record statistics (and the consistency check) read: ``STRIDE``, less on a
    record too short for ``ROWS_PER_MODE`` rows per POD mode (a basis that spans every row it is read on leaves
    no residual: 501 samples at a stride of 16 are 32 rows, fewer than 40 modes)."""
    return max(1, min(STRIDE, n_samples // (ROWS_PER_MODE * max(1, n_modes))))


class FullSignalCheck(nn.Module):
    """Out-of-distribution flag of full records from their POD residual, roughness and plateau.

    Args:
        modes: POD modes (n_e, n_m).   mean: mean record (n_e,) [A].
        stride: use every ``stride``-th sample for the POD residual (>= 1; None: :func:`record_stride`).
        residual_threshold: POD residual (fraction) above which a record is foreign (inf: never).
        roughness_threshold: roughness above which a record is noise-dominated (``phm-train`` raises it above
            the training records' own where the sampling is coarse).
        plateau_threshold: plateau fraction above which a record is clipped; raised to
            ``PLATEAU_MIN_POINTS`` sampled points where the record has too few for it (``phm-train`` also
            raises it above the training records' own, :func:`~.ood_calibration.shape_thresholds`).
        plateau_tolerance: distance from the maximum, as a fraction of the record's range, that counts
            as "on the plateau".
    """

    def __init__(
        self,
        modes: torch.Tensor,
        mean: torch.Tensor,
        stride: int | None = None,
        residual_threshold: float = float("inf"),
        roughness_threshold: float = DEFAULT_ROUGHNESS_THRESHOLD,
        plateau_threshold: float = DEFAULT_PLATEAU_THRESHOLD,
        plateau_tolerance: float = 1e-3,
    ):
        super().__init__()
        if modes.dim() != 2 or mean.shape != modes.shape[:1]:
            raise ValueError(
                f"modes (n_e, n_m) and mean (n_e,) expected, got {tuple(modes.shape)} and {tuple(mean.shape)}"
            )
        if stride is None:
            stride = record_stride(int(modes.shape[0]), int(modes.shape[1]))
        if isinstance(stride, bool) or not isinstance(stride, int) or stride < 1:
            raise ValueError(f"full_signal_check.stride must be an integer >= 1, got {stride!r}")
        for name, value in (
            ("residual_threshold", residual_threshold),
            ("roughness_threshold", roughness_threshold),
            ("plateau_threshold", plateau_threshold),
            ("plateau_tolerance", plateau_tolerance),
        ):
            if not float(value) > 0:
                raise ValueError(f"full_signal_check.{name} must be > 0, got {value!r}")
        rows = torch.arange(0, modes.shape[0], stride)
        q, _ = torch.linalg.qr(modes[rows].to(torch.float64))
        self.register_buffer("rows", rows)
        # the shape statistics sample at a jittered stride: a ripple at a multiple of sample_rate / stride
        # would alias to a constant on a regular one (a false plateau)
        jitter = torch.randint(0, stride, rows.shape, generator=torch.Generator().manual_seed(0))
        shape_rows = (rows + jitter).clamp(max=modes.shape[0] - 2)
        self.register_buffer("shape_rows", shape_rows)
        self.register_buffer("next_rows", shape_rows + 1)
        self.register_buffer("basis", q.to(modes.dtype))  # (n_e / stride, n_m), orthonormal
        self.register_buffer("mean_rows", mean[rows].to(modes.dtype))
        self.n_full = int(modes.shape[0])
        self.residual_threshold = float(residual_threshold)
        self.roughness_threshold = float(roughness_threshold)
        self.plateau_threshold = max(float(plateau_threshold), PLATEAU_MIN_POINTS / float(rows.shape[0]))
        self.plateau_tolerance = float(plateau_tolerance)

    def _check(self, signals: torch.Tensor) -> None:
        if signals.dim() != 2 or signals.shape[1] != self.n_full:
            raise ValueError(f"full_signal_check: records must be (B, {self.n_full})")

    @torch.jit.export
    def statistics(self, signals: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """(POD residual, roughness, plateau), each (B,), of full records (B, n_e) [A] from one gather of the
        samples the three read: a batch of full records does not fit in cache, so each separate gather was a
        pass over memory (three of the step's four passes)."""
        self._check(signals)
        n = self.rows.shape[0]
        cols = signals.index_select(1, torch.cat([self.rows, self.shape_rows, self.next_rows])).to(self.basis.dtype)
        return (
            self._residual(cols[:, :n]),
            self._roughness(cols[:, n : 2 * n], cols[:, 2 * n :]),
            self._plateau(cols[:, n : 2 * n]),
        )

    @torch.jit.export
    def residual(self, signals: torch.Tensor) -> torch.Tensor:
        """POD residual r (B,) in [0, 1] of full records (B, n_e) [A]; NaN where a used sample is not finite."""
        self._check(signals)
        return self._residual(signals.index_select(1, self.rows).to(self.basis.dtype))

    def _residual(self, x: torch.Tensor) -> torch.Tensor:
        d = x - self.mean_rows
        energy = d.pow(2).sum(1)
        explained = (d @ self.basis).pow(2).sum(1)
        return ((energy - explained).clamp(min=0.0) / energy.clamp(min=1e-30)).sqrt()

    @torch.jit.export
    def roughness(self, signals: torch.Tensor) -> torch.Tensor:
        """RMS(diff) / RMS(about the mean), (B,); NaN for a flat record (its plateau is 1) or a non-finite one.

        Estimated on the ``stride``-th samples and their right neighbours (adjacent pairs, so the step is
        the full-rate one): a full pass over every sample would halve the batched throughput."""
        self._check(signals)
        x = signals.index_select(1, self.shape_rows).to(self.basis.dtype)
        return self._roughness(x, signals.index_select(1, self.next_rows).to(self.basis.dtype))

    def _roughness(self, x: torch.Tensor, after: torch.Tensor) -> torch.Tensor:
        step = (after - x).pow(2).mean(1).sqrt()
        spread = (x - x.mean(1, keepdim=True)).pow(2).mean(1).sqrt()
        return step / spread

    @torch.jit.export
    def plateau(self, signals: torch.Tensor) -> torch.Tensor:
        """Fraction (B,) of the (jittered) ``stride``-th samples within ``plateau_tolerance`` x range of their
        maximum."""
        self._check(signals)
        return self._plateau(signals.index_select(1, self.shape_rows).to(self.basis.dtype))

    def _plateau(self, x: torch.Tensor) -> torch.Tensor:
        top = x.amax(1, keepdim=True)
        span = top - x.amin(1, keepdim=True)
        return (x >= top - self.plateau_tolerance * span).to(x.dtype).mean(1)

    def forward(self, signals: torch.Tensor) -> torch.Tensor:
        """Out-of-distribution flag (B,) bool of full records (B, n_e) [A].

        A record with a non-finite sample compares False on every statistic: the pipeline's gappy checks
        (missing-sample count, residual) decide for it.
        """
        residual, roughness, plateau = self.statistics(signals)
        return (
            (residual > self.residual_threshold)
            | (roughness > self.roughness_threshold)
            | (plateau > self.plateau_threshold)
        )
