"""The damage law as the tracker's process model: dk/dt = s F (k - k0) + eps.

s is the actuator's wear-rate scale (lognormal, median 1, log-std ``rate_scale_sigma``), eps an i.i.d. normal
rate per component (std ``noise_std`` [1/h]) held constant over blocks of ``noise_correlation_hours``. The ODE
is linear, so between inspections the noise-free part is exact: k(t + dt) - k0 = expm(s F dt) (k(t) - k0).
The block phase of eps is unknown to the tracker: its integral over dt is taken with the variance of a
random-phase block process (triangular autocorrelation of width T_c),

    Var(int_0^dt eps) = std^2 (dt^2 - dt^3 / (3 T_c))   for dt <= T_c,
                        std^2 (dt T_c - T_c^2 / 3)      for dt >= T_c,

which is the exact variance when the block boundaries fall uniformly at random (dt << T_c: one block, a
constant rate, std dt; dt >> T_c: a random walk of T_c-long steps).
"""

from __future__ import annotations

import functools
import logging
import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import torch

from ..faults import N_FAULTS

log = logging.getLogger(__name__)

TAYLOR_NORM = 1.0 / 64  # ||r F|| of the short Taylor step: 7 terms reach 1e-16 of the vector
TAYLOR_TERMS = 7
TABLE_MAX = 1 << 15  # entries of the expm(j h F) table (beyond it: more short sub-steps)


@dataclass(frozen=True)
class DamageLaw:
    """Process model of the tracker.

    Args:
        rate: F (8, 8) [1/h], float64.
        nominal: k0 (8,), the actuator's nominal fault vector.
        noise_std: std of eps per component (8,) [1/h].
        noise_correlation_hours: block length T_c of eps [h].
        rate_scale_sigma: log-std of the wear-rate scale s (the prior of log s is N(0, sigma^2)).
        horizon_hours: the pipeline's RUL horizon [h] (a bound at or beyond it is censored).
    """

    rate: torch.Tensor
    nominal: torch.Tensor
    noise_std: torch.Tensor
    noise_correlation_hours: float
    rate_scale_sigma: float
    horizon_hours: float

    def __post_init__(self) -> None:
        if tuple(self.rate.shape) != (N_FAULTS, N_FAULTS) or not bool(torch.isfinite(self.rate).all()):
            raise ValueError(f"damage.rate must be a finite 8x8 matrix, got shape {tuple(self.rate.shape)}")
        if tuple(self.noise_std.shape) != (N_FAULTS,) or bool((self.noise_std < 0).any()):
            raise ValueError(f"damage.noise_std must be 8 values >= 0, got {self.noise_std.tolist()}")
        if tuple(self.nominal.shape) != (N_FAULTS,):
            raise ValueError(f"nominal must have 8 entries, got {self.nominal.tolist()}")
        for name in ("noise_correlation_hours", "horizon_hours"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0):
                raise ValueError(f"damage.{name} must be > 0, got {value!r}")
        if not (math.isfinite(self.rate_scale_sigma) and self.rate_scale_sigma >= 0):
            raise ValueError(f"damage.rate_scale_sigma must be >= 0, got {self.rate_scale_sigma!r}")

    @classmethod
    def from_config(cls, damage: Mapping[str, Any], model: Any, source: str) -> DamageLaw:
        """The law of a damage config (``conf/damage`` keys) for the exported pipeline ``model``: k0 and the
        horizon are the pipeline's (``nominal``, ``times[-1]``), and F must reproduce its propagators
        (``propagators[1] = expm(F step)``), else a ValueError naming ``source``."""
        missing = [k for k in ("rate", "noise_std", "noise_correlation_hours") if k not in damage]
        if missing:
            raise ValueError(f"damage config ({source}) lacks {missing}")
        sigma = damage.get("rate_scale_sigma")
        if sigma is None:
            log.warning(
                "damage config (%s) has no rate_scale_sigma: the wear-rate scale s is held at 1 (the "
                "law before the rate scale existed)",
                source,
            )
        law = cls(
            torch.tensor(damage["rate"], dtype=torch.float64),
            model.nominal.detach().to(torch.float64).clone(),
            torch.tensor(damage["noise_std"], dtype=torch.float64),
            float(damage["noise_correlation_hours"]),
            0.0 if sigma is None else float(sigma),
            float(model.times[-1]),
        )
        law.check_pipeline(model, source)
        return law

    def check_pipeline(self, model: Any, source: str) -> None:
        """F must reproduce the pipeline's first propagator step (float32 pipelines: to 1e-5)."""
        times, props = model.times.to(torch.float64), model.propagators.to(torch.float64)
        step = float(times[1] - times[0])
        expected = torch.linalg.matrix_exp(self.rate * step)
        err = float((props[1] - expected).abs().max())
        if err > 1e-5:
            raise ValueError(
                f"damage config ({source}): its rate F does not match the pipeline's propagators "
                f"(max |expm(F {step:g} h) - propagator| = {err:.3g}); give the damage config the "
                f"pipeline was exported with"
            )

    @functools.cached_property
    def _norm(self) -> float:
        return float(torch.linalg.matrix_norm(self.rate, ord=1))

    @functools.cached_property
    def _table_step(self) -> float:
        """h [h] of the table: ||h F||_1 = ``TAYLOR_NORM``."""
        return TAYLOR_NORM / self._norm if self._norm > 0 else math.inf

    def _table(self, tau_max: float) -> torch.Tensor:
        """expm(j h F) (n, 8, 8) for j h up to at least ``tau_max`` (grown by doubling, at most ``TABLE_MAX``)."""
        table = self.__dict__.get("_expm_table")
        n = min(TABLE_MAX, math.ceil(tau_max / self._table_step) + 1)
        if table is None or table.shape[0] < n:
            size = max(n, 2 * (0 if table is None else table.shape[0]), 64)
            size = min(size, TABLE_MAX)
            j = torch.arange(size, dtype=torch.float64) * self._table_step
            table = torch.linalg.matrix_exp(self.rate * j.view(-1, 1, 1))
            self.__dict__["_expm_table"] = table  # a cache of the frozen law (not a field)
        return table

    def propagate(self, dk: torch.Tensor, tau: torch.Tensor) -> torch.Tensor:
        """expm(tau F) dk: dk (N, 8) deviations from k0, tau (N,) wear-clock times s dt [h] -> (N, 8).

        expm(tau F) = expm(j h F) expm(r F) with j h the nearest table time below tau (:meth:`_table`) and r the
        rest, applied to the vectors as a Taylor series in as many sub-steps as keep ||r F|| <= ``TAYLOR_NORM``
        (one inside the table): no matrix exponential per particle, 7 short terms instead of a long series."""
        tau = tau.to(dk.dtype)
        if not tau.numel() or self._norm == 0.0:
            return dk.clone()
        f = self.rate.to(dk.dtype)
        table = self._table(float(tau.abs().max()))
        j = torch.div(tau, self._table_step, rounding_mode="floor").long().clamp(0, table.shape[0] - 1)
        rest = tau - j.to(tau) * self._table_step
        steps = max(1, math.ceil(float(rest.abs().max()) * self._norm / TAYLOR_NORM - 1e-9))
        h = (rest / steps).unsqueeze(-1)
        out = dk
        for _ in range(steps):
            term, total = out, out
            for n in range(1, TAYLOR_TERMS + 1):
                term = (term @ f.T) * h / n
                total = total + term
            out = total
        return (table[j].to(dk.dtype) @ out.unsqueeze(-1)).squeeze(-1)

    def expm(self, tau: torch.Tensor) -> torch.Tensor:
        """expm(tau F) (N, 8, 8) for wear-clock times tau (N,) [h]: the table entry below tau times the Taylor
        polynomial of the rest (as :meth:`propagate`, for a filter that moves a covariance too)."""
        tau = tau.to(torch.float64)
        n = self.rate.shape[0]
        eye = torch.eye(n, dtype=torch.float64)
        if not tau.numel() or self._norm == 0.0:
            return eye.expand(tau.shape[0], n, n).clone()
        table = self._table(float(tau.abs().max()))
        j = torch.div(tau, self._table_step, rounding_mode="floor").long().clamp(0, table.shape[0] - 1)
        rest = tau - j.to(tau) * self._table_step
        steps = max(1, math.ceil(float(rest.abs().max()) * self._norm / TAYLOR_NORM - 1e-9))
        h = rest / steps
        powers = self._powers  # (T + 1, 8, 8): F^n / n!
        coef = h.unsqueeze(-1) ** torch.arange(TAYLOR_TERMS + 1, dtype=torch.float64)  # (N, T + 1)
        step = (coef @ powers.reshape(TAYLOR_TERMS + 1, -1)).reshape(-1, n, n)
        out = step
        for _ in range(steps - 1):
            out = out @ step
        return table[j] @ out

    @functools.cached_property
    def _powers(self) -> torch.Tensor:
        out = [torch.eye(self.rate.shape[0], dtype=torch.float64)]
        for k in range(1, TAYLOR_TERMS + 1):
            out.append(out[-1] @ self.rate / k)
        return torch.stack(out)

    def noise_std_over(self, dt: torch.Tensor) -> torch.Tensor:
        """Std (N, 8) [-] of int eps over intervals dt (N,) [h] (random block phase; module docstring)."""
        tc = self.noise_correlation_hours
        dt = dt.to(torch.float64).clamp(min=0.0).unsqueeze(-1)
        var = torch.where(dt <= tc, dt**2 - dt**3 / (3.0 * tc), dt * tc - tc**2 / 3.0)
        return self.noise_std.to(dt) * var.clamp(min=0.0).sqrt()


def band_includes_rate_scale(metadata: Mapping[str, Any]) -> bool:
    """Whether an exported pipeline's RUL band holds the spread of wear rates between actuators: its metadata's damage
    config (the law phm-evaluate calibrated the band with) has a wear-rate scale, ``rate_scale_sigma`` > 0, so the
    calibration's Monte Carlo drew one s per run. A pipeline exported before the scale existed (the shipped one) or
    with it at 0 has a band of the rate disturbance eps alone."""
    damage = metadata.get("damage")
    sigma = damage.get("rate_scale_sigma") if isinstance(damage, Mapping) else None
    return sigma is not None and float(sigma) > 0


def damage_config(
    metadata: Mapping[str, Any], fallback: Mapping[str, Any] | None, source: str
) -> tuple[dict[str, Any], str]:
    """The damage config of an exported pipeline: its metadata's ``damage`` (written by phm-export since the
    tracker exists), else ``fallback`` (the composed ``conf/damage``) with a warning; (config, where from)."""
    damage = metadata.get("damage")
    if isinstance(damage, Mapping):
        return dict(damage), f"{source} metadata"
    if fallback is None:
        raise ValueError(f"{source} carries no damage config (exported before phm-export wrote it) and none was given")
    log.warning(
        "%s carries no damage config (exported before phm-export wrote it): using the composed "
        "conf/damage; check it is the one the pipeline was exported with",
        source,
    )
    return dict(fallback), "conf/damage"
