"""The RUL band of a *measured* k_hat: the FDI error joins the physics spread.

The physics band (``deltas`` x ``direction``, :class:`~phm_torch.prognostics.DeterministicRUL`) is the
spread of the RUL from a *known* k. Online, k is an FDI estimate, and near nominal its error dominates:
the damage grows roughly exponentially, so an error of 0.02 on a true 0.001 halves the RUL. A band
without it is overconfident (on the paper run, 6 % of the true RULs fell inside the physics-only band).

So the full-flow propagations start from k_hat with its damage moved by
``delta_q u + eta_q s`` per quantile q, where s (8,) is the FDI error scale (mean |k_hat - k| per growing
component, measured on held-out signals) and eta_q a multiple of it, calibrated by bisection on those
signals against the RUL of their true k:

* eta_5: 95 % of the true-k RULs lie above the 5 % bound;
* eta_95: 95 % lie below the 95 % bound;
* eta_50 = 0 by default: the median is k_hat's own propagation. ``correct_median=True`` calibrates it
  instead so that the median ratio of the full-flow median RUL to the true-k RUL is 1 (removing the
  FDI bias toward damage near nominal). That shift does not transfer between fault distributions:
  calibrated on ``val`` and evaluated on the near-nominal ``rul`` split it took the median error from
  47 % to 25 % on the paper run, but from 25 % to 390 % on the default run (600 training signals), by
  pulling k_hat onto nominal, where the RUL is the horizon. An overestimated RUL is the unsafe side,
  so it is off unless asked for.

Where the verdict classifier g stops a bound's propagations, the bound can fail to cover whatever eta: an FDI
that cannot identify a component (the rudder actuator's eccentricity under its chirp, R^2 0.11) returns its
prior for it, g learns nothing about that component's true value, and calls even
the nominal vector faulty, so no shift towards nominal lengthens the RUL (measured: the 270 V rudder
actuator's 95 % bound ended on the bracket, band coverage 19 %). That bound's bisection is then repeated with
its propagations stopped by the health classifier f, which knows the true k: its shifted starts are
hypotheses about the true k (``health_stop``; :meth:`OnlinePipeline.set_health_stop`).

The calibration signals must not be the ones the band is evaluated on (``phm-evaluate`` uses ``val``
and evaluates on ``rul``), and may be corrupted with measurement noise so that the band also covers it.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from .pipeline import OnlinePipeline


class TooFewCalibrationSignals(ValueError):
    """Fewer usable calibration signals than ``min_used``: the band cannot be calibrated."""


@dataclass
class FDIBand:
    """Calibrated FDI disturbances.

    Attributes:
        deltas: (3,) eta_5, eta_50, eta_95 in units of ``direction`` (larger = more damage).
        direction: (8,) FDI error scale s: mean |k_hat - k| per component, 0 for a non-growing one.
        n_used: calibration signals used (in distribution, healthy under the true k).
        saturated: per quantile, whether the bisection ended on the bracket (after the switch below).
        health_stop: quantiles (0: 5 %, 2: 95 %) whose verdict-stopped bisection ended on its non-covering
            bracket end and that the health classifier stops instead (set on the pipeline).
    """

    deltas: torch.Tensor
    direction: torch.Tensor
    n_used: int
    saturated: list[bool]
    health_stop: list[int]


def calibrate_fdi_band(
    pipeline: OnlinePipeline,
    signals: torch.Tensor,
    k: torch.Tensor,
    coverage: float = 0.9,
    bracket: float = 20.0,
    iterations: int = 30,
    min_used: int = 10,
    correct_median: bool = False,
) -> FDIBand:
    """Calibrate the FDI band of ``pipeline`` on held-out records.

    Args:
        pipeline: the online pipeline with its physics ``deltas`` already set.
        signals: (N, n_full) or (N, n_points) held-out envelope currents [A] (may carry noise / NaN).
        k: (N, 8) their true fault vectors.
        coverage: target two-sided coverage of the band (0.9 for 5-95 %).
        bracket: |eta| bound, in multiples of the error scale.
        iterations: bisection steps per quantile.
        min_used: fewest usable signals (in distribution, healthy under their true k), else
            :class:`TooFewCalibrationSignals`.
        correct_median: also calibrate eta_50 (see the module docstring); False keeps it 0.
    """
    if not 0.0 < coverage < 1.0:
        raise ValueError(f"fdi_band.coverage must be in (0, 1), got {coverage!r}")
    if not bracket > 0:
        raise ValueError(f"fdi_band.bracket must be > 0, got {bracket!r}")
    if signals.shape[0] != k.shape[0] or k.dim() != 2 or k.shape[1] != 8:
        raise ValueError(
            f"fdi_band: signals (N, n) and k (N, 8) expected, got {tuple(signals.shape)} and {tuple(k.shape)}"
        )
    dtype = pipeline.times.dtype
    with torch.no_grad():
        k_hat, _, _, ood, _ = pipeline(signals.to(dtype))
        k = k.to(dtype)
        target = pipeline.rul(k)[:, 1]
        keep = (~ood) & (target > 0)
        if int(keep.sum()) < min_used:
            raise TooFewCalibrationSignals(
                f"fdi_band: only {int(keep.sum())} of {k.shape[0]} calibration signals are in distribution and "
                f"healthy under their true k; at least {min_used} are needed"
            )
        k, k_hat, target = k[keep], k_hat[keep], target[keep]
        scale = (k_hat - k).abs().mean(0) * (pipeline.direction > 0).to(dtype)
        tail = 0.5 * (1.0 - coverage)
        pipeline.set_health_stop(None)
        deltas, saturated = _bisect_all(pipeline, k_hat, scale, target, tail, bracket, iterations, correct_median)
        # the 5 % bound fails to cover at +bracket (more damage), the 95 % bound at -bracket (less damage)
        stuck = [j for j, sign in ((0, 1.0), (2, -1.0)) if saturated[j] and deltas[j] * sign > 0]
        if stuck:
            pipeline.set_health_stop(stuck)
            again, again_saturated = _bisect_all(
                pipeline, k_hat, scale, target, tail, bracket, iterations, correct_median, only=stuck
            )
            for j in stuck:
                deltas[j], saturated[j] = again[j], again_saturated[j]
    return FDIBand(
        torch.tensor(deltas, dtype=torch.float64), scale.to(torch.float64), int(keep.sum()), saturated, stuck
    )


def _bisect_all(
    pipeline: OnlinePipeline,
    k_hat: torch.Tensor,
    scale: torch.Tensor,
    target: torch.Tensor,
    tail: float,
    bracket: float,
    iterations: int,
    correct_median: bool,
    only: list[int] | None = None,
) -> tuple[list[float], list[bool]]:
    """eta_5, eta_50 (0 unless ``correct_median``), eta_95 by bisection, and whether each ended on the
    bracket; ``only``: bisect these quantiles, 0 (unsaturated) for the others."""
    dtype = k_hat.dtype

    def rul_at(j: int, eta: float) -> torch.Tensor:
        return pipeline.propagations(k_hat, torch.full((3,), eta, dtype=dtype), scale, True)[:, j]

    # each objective rises with eta (more damage, shorter RUL); the coverage bounds keep the bracket end
    # on their covering side (the statistic is a step function of eta), the median the midpoint
    objectives = (
        (lambda eta: float((target >= rul_at(0, eta)).to(dtype).mean()) - (1.0 - tail), "hi"),
        (lambda eta: 1.0 - float((rul_at(1, eta) / target).median()), "mid"),
        (lambda eta: (1.0 - tail) - float((target <= rul_at(2, eta)).to(dtype).mean()), "lo"),
    )
    deltas, saturated = [], []
    for j, (objective, side) in enumerate(objectives):
        if (j == 1 and not correct_median) or (only is not None and j not in only):
            deltas.append(0.0)
            saturated.append(False)
            continue
        lo, hi = -bracket, bracket
        for _ in range(iterations):
            mid = 0.5 * (lo + hi)
            if objective(mid) < 0:
                lo = mid
            else:
                hi = mid
        eta = {"lo": lo, "hi": hi, "mid": 0.5 * (lo + hi)}[side]
        deltas.append(eta)
        saturated.append(bool(abs(abs(eta) - bracket) < 1e-6 * bracket))
    return deltas, saturated
