"""Damage propagation dk/dt = s F (k - k0) + eps, integrated with torchdiffeq (seed paper, §5 of the datasheet).

Time is in flight hours. eps is i.i.d. normal per component, held constant over blocks of
``noise_correlation_hours`` and redrawn between them (a rate disturbance of finite correlation time,
which a deterministic ODE solver can integrate exactly block by block).

s is a per-actuator wear-rate scale, lognormal with median 1 and log-std ``rate_scale_sigma``: two
actuators of one type do not wear at one rate (manufacturing scatter of fits and insulation, each
airframe's own mission mix). It is constant over an actuator's life, unlike eps, so it does not average
out: without eps, k(t; s F) = k(s t; F) and the RUL is RUL(s = 1) / s. ``rate_scale_sigma = 0`` is the
datasheet's law (s = 1).
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import torch
from torchdiffeq import odeint

from ..faults import N_FAULTS

PHASE_INDEX = 6  # k7 is a phase, never a damage


class DamageModel:
    """Linear damage growth with per-block random rates and a per-actuator wear-rate scale.

    Args:
        rate: F (8, 8) [1/h]; row i = growth of k_i, column j = influence of Delta k_j.
        noise_std: std of eps per component (8,) [1/h].
        noise_correlation_hours: length of the blocks over which eps is constant [h].
        horizon_hours: longest time integrated [h].
        step_hours: integration / event-search grid [h].
        nominal: k0 (8,), the actuator's nominal fault vector (``ActuatorParams.nominal_faults``).
        rate_scale_sigma: log-std of the wear-rate scale s ~ lognormal(0, sigma) [-]; 0 = every actuator
            wears at F (the datasheet's law).
    """

    def __init__(
        self,
        rate: Sequence[Sequence[float]],
        noise_std: Sequence[float],
        noise_correlation_hours: float,
        horizon_hours: float,
        step_hours: float,
        nominal: Sequence[float],
        rate_scale_sigma: float = 0.0,
    ):
        f = torch.as_tensor(rate, dtype=torch.float64)
        if f.shape != (N_FAULTS, N_FAULTS) or not torch.isfinite(f).all():
            raise ValueError(f"damage.rate must be a finite 8x8 matrix, got shape {tuple(f.shape)}")
        if f[PHASE_INDEX].abs().sum() > 0 or f[:, PHASE_INDEX].abs().sum() > 0:
            raise ValueError("damage.rate: row and column 7 (eccentricity phase k7) must be zero")
        sd = torch.as_tensor(noise_std, dtype=torch.float64)
        if sd.shape != (N_FAULTS,) or (sd < 0).any() or not torch.isfinite(sd).all():
            raise ValueError(f"damage.noise_std must be 8 finite values >= 0, got {list(noise_std)}")
        if sd[PHASE_INDEX] != 0:
            raise ValueError(f"damage.noise_std[6] (k7) must be 0, got {float(sd[PHASE_INDEX])}")
        for name, v in (
            ("noise_correlation_hours", noise_correlation_hours),
            ("horizon_hours", horizon_hours),
            ("step_hours", step_hours),
        ):
            if not (math.isfinite(v) and v > 0):
                raise ValueError(f"damage.{name} must be > 0, got {v}")
        if step_hours > horizon_hours:
            raise ValueError(f"damage.step_hours ({step_hours}) must not exceed horizon_hours ({horizon_hours})")
        if (
            isinstance(rate_scale_sigma, bool)
            or not isinstance(rate_scale_sigma, (int, float))
            or not (math.isfinite(rate_scale_sigma) and 0.0 <= rate_scale_sigma <= 2.0)
        ):
            # sigma 2 already spans a factor 700 between the 5 % and 95 % actuators: beyond is a typo
            raise ValueError(f"damage.rate_scale_sigma must be a number in [0, 2], got {rate_scale_sigma!r}")
        self.rate, self.noise_std = f, sd
        self.rate_scale_sigma = float(rate_scale_sigma)
        self.block = float(noise_correlation_hours)
        self.horizon, self.step = float(horizon_hours), float(step_hours)
        self.nominal = torch.as_tensor(nominal, dtype=torch.float64)
        if self.nominal.shape != (N_FAULTS,):
            raise ValueError(f"damage.nominal must have 8 entries, got {list(nominal)}")

    @property
    def grid(self) -> torch.Tensor:
        """Time grid [h] (T,) from 0 to the horizon."""
        n = math.ceil(self.horizon / self.step)
        return torch.arange(n + 1, dtype=torch.float64) * self.step

    def sample_noise(
        self, batch: int, generator: torch.Generator | None = None, hours: float | None = None
    ) -> torch.Tensor:
        """eps per block: (batch, n_blocks, 8) [1/h], blocks covering ``hours`` (default: the horizon)."""
        hours = self.horizon if hours is None else float(hours)
        n_blocks = math.ceil(hours / self.block) + 1
        z = torch.randn(batch, n_blocks, N_FAULTS, generator=generator, dtype=torch.float64)
        return z * self.noise_std

    def sample_rate_scale(self, batch: int, generator: torch.Generator | None = None) -> torch.Tensor:
        """Wear-rate scales s (batch,) [-], lognormal with median 1 and log-std ``rate_scale_sigma``.

        With ``rate_scale_sigma = 0`` the scales are ones and nothing is drawn from ``generator`` (the
        random streams of the datasheet's law are unchanged).
        """
        if self.rate_scale_sigma == 0.0:
            return torch.ones(batch, dtype=torch.float64)
        z = torch.randn(batch, generator=generator, dtype=torch.float64)
        return torch.exp(self.rate_scale_sigma * z)

    def _rhs(self, eps: torch.Tensor | None, scale: torch.Tensor | None = None):
        f, k0, block = self.rate, self.nominal, self.block

        def rhs(t: torch.Tensor, k: torch.Tensor) -> torch.Tensor:
            dk = (k - k0.to(k)) @ f.to(k).T
            if scale is not None:
                dk = dk * scale.to(k).unsqueeze(-1)
            if eps is not None:
                i = torch.clamp((t / block).floor().long(), max=eps.shape[1] - 1)
                dk = dk + eps[:, i].to(k)
            return dk

        return rhs

    def integrate(
        self,
        k0: torch.Tensor,
        eps: torch.Tensor | None = None,
        t: torch.Tensor | None = None,
        method: str = "rk4",
        scale: torch.Tensor | None = None,
    ) -> torch.Tensor:
        """k(t) on the grid with torchdiffeq: k0 (B, 8) -> (T, B, 8).

        ``scale``: the wear-rate scale s per sample (B,) (None: s = 1). The fixed-step solver steps exactly
        on the grid; the grid step divides the noise block, so each step sees one eps (exact for RK4 up to
        its truncation error, negligible at s F * step << 1).
        """
        t = self.grid if t is None else t
        if scale is not None:
            scale = torch.as_tensor(scale, dtype=torch.float64).reshape(-1)
            if scale.shape[0] != k0.shape[0] or not (torch.isfinite(scale).all() and (scale > 0).all()):
                raise ValueError(
                    f"damage.integrate: scale must be (B,) = ({k0.shape[0]},) finite values > 0, "
                    f"got shape {tuple(scale.shape)}"
                )
        if eps is not None and abs(self.block / self.step - round(self.block / self.step)) > 1e-9:
            raise ValueError(
                f"damage.noise_correlation_hours ({self.block}) must be a multiple of step_hours ({self.step})"
            )
        return odeint(
            self._rhs(eps, scale),
            k0.to(torch.float64),
            t.to(torch.float64),
            method=method,
            options={"step_size": self.step} if method in ("rk4", "euler", "midpoint") else None,
        )

    def transitions(self, t: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Exact propagators of the linear ODE with constant eps and s = 1: k(t) - k0 = A(t) dk0 + B(t) eps.

        Returns A(t) = expm(F t) and B(t) = int_0^t expm(F u) du, each (T, 8, 8). Used by the online
        pipeline (no solver loop at run time); tests check them against :meth:`integrate`. A wear-rate
        scale s is a clock change: A_s(t) = A(s t), B_s(t) = B(s t) / s.
        """
        n = N_FAULTS
        m = torch.zeros(t.numel(), 2 * n, 2 * n, dtype=torch.float64)
        m[:, :n, :n] = self.rate * t.view(-1, 1, 1)
        m[:, :n, n:] = torch.eye(n, dtype=torch.float64) * t.view(-1, 1, 1)
        e = torch.linalg.matrix_exp(m)
        return e[:, :n, :n], e[:, :n, n:]
