"""Particle filter over (k, log s) per actuator, batched in torch across particles and actuators.

State of one actuator: P equally weighted particles, each a fault vector k (8,) and a log wear-rate scale
log s. One inspection at hours h with the pipeline's estimate k_hat and its error scale:

1. *initialise* (first fused inspection of a track, or a ``restart`` after maintenance): k ~ k_hat + scale z
   reflected into [0, 1], log s ~ N(0, sigma_s^2) (the fleet prior of the damage law);
2. *predict* from the previous inspection (dt = h - h_prev): the exact noise-free propagation
   expm(s F dt) of each particle with its own s, eps added at mid-interval with the variance of the
   block-constant rate (:class:`~.damage_law.DamageLaw`), k clamped to [0, 1];
3. *update* (in-distribution inspections only; an OOD one stops after the prediction, ``fused`` false):
   weights from the measurement model (:mod:`.measurement`), systematic resampling, a Liu-West kernel step
   (:mod:`.resampling`), log s held within +/- log(max_rate_scale).

k7, the eccentricity phase, has no rate and no eps: it is a constant the measurements refine.

Random numbers come from a generator seeded by (seed, actuator, inspection number), so an actuator's track
does not depend on which other actuators share its batch, and a resumed run draws what an uninterrupted one
would.
"""

from __future__ import annotations

import hashlib
import math
from collections.abc import Sequence
from dataclasses import dataclass

import torch

from .damage_law import N_FAULTS, DamageLaw
from .measurement import log_likelihood
from .particle_rul import ParticleRUL
from .resampling import liu_west, systematic_indices

D = N_FAULTS + 1     # particle dimension: k (8) and log s


@dataclass
class TrackerSettings:
    """Settings of the tracker (the ``tracker`` node of conf/track.yaml).

    Args:
        n_particles: particles per actuator.
        rul_particles: particles (every P / this one) whose RUL makes the 5/50/95 % band.
        seed: base seed of the per-(actuator, inspection) generators.
        measurement_dof: Student-t degrees of freedom of the k_hat error (inf: Gaussian).
        shrink: Liu-West a in (0, 1] (1: no kernel step).
        max_rate_scale: the particles' s stays within [1 / this, this].
        bisections: halvings of the RUL crossing interval.
    """

    n_particles: int = 512
    rul_particles: int = 128
    seed: int = 0
    measurement_dof: float = 10.0
    shrink: float = 0.8
    max_rate_scale: float = 8.0
    bisections: int = 6

    def __post_init__(self) -> None:
        for name in ("n_particles", "rul_particles", "seed", "bisections"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or value < (0 if name in ("seed", "bisections")
                                                                                  else 2):
                raise ValueError(f"tracker.{name} must be an integer >= {0 if name in ('seed', 'bisections') else 2}"
                                 f", got {value!r}")
        if self.n_particles % self.rul_particles:
            raise ValueError(f"tracker.rul_particles ({self.rul_particles}) must divide tracker.n_particles "
                             f"({self.n_particles})")
        self.measurement_dof = float(self.measurement_dof)
        if not self.measurement_dof > 0:
            raise ValueError(f"tracker.measurement_dof must be > 0 (inf: Gaussian), got {self.measurement_dof!r}")
        if not 0.0 < float(self.shrink) <= 1.0:
            raise ValueError(f"tracker.shrink must be in (0, 1], got {self.shrink!r}")
        if not float(self.max_rate_scale) > 1.0:
            raise ValueError(f"tracker.max_rate_scale must be > 1, got {self.max_rate_scale!r}")


@dataclass
class Posterior:
    """Summaries of a batch of actuators after one inspection (NaN rows: no track yet).

    k_mean, k_low, k_high: (B, 8) posterior mean and 5/95 % of k.  rate_scale: (B, 3) 5/50/95 % of s.
    rul: (B, 3) [h] 5/50/95 % of the RUL, NaN where censored (or no track).  censored: (B, 3) bool.
    tracked: (B,) bool, whether the actuator has particles.
    """

    k_mean: torch.Tensor
    k_low: torch.Tensor
    k_high: torch.Tensor
    rate_scale: torch.Tensor
    rul: torch.Tensor
    censored: torch.Tensor
    tracked: torch.Tensor


def actuator_seed(seed: int, actuator: str, step: int) -> int:
    """A 63-bit seed for one actuator's ``step``-th inspection (stable across runs and batches)."""
    digest = hashlib.blake2b(f"{seed}/{actuator}/{step}".encode(), digest_size=8).digest()
    return int.from_bytes(digest, "little") >> 1


def reflect_unit(x: torch.Tensor) -> torch.Tensor:
    """x reflected into [0, 1] (an initial draw near a bound keeps its density instead of piling on it)."""
    x = torch.remainder(x, 2.0)
    return torch.where(x > 1.0, 2.0 - x, x)


class Tracker:
    """Particle filter of a fleet.

    Args:
        law: the damage law (process model).
        rul: the per-particle RUL (:class:`~.particle_rul.ParticleRUL`); None: no RUL (NaN).
        settings: :class:`TrackerSettings`.

    State per actuator id (rows of ``k`` (A, P, 8), ``log_s`` (A, P), ``hours`` (A,) [h], ``steps`` (A,)
    inspections seen, ``tracked`` (A,) bool); :meth:`state` / :meth:`load_state` move one actuator's in and out.
    """

    def __init__(self, law: DamageLaw, rul: ParticleRUL | None, settings: TrackerSettings | None = None):
        self.law, self.rul_model = law, rul
        self.settings = settings or TrackerSettings()
        p = self.settings.n_particles
        self.rows: dict[str, int] = {}
        self.k = torch.zeros(0, p, N_FAULTS, dtype=torch.float64)
        self.log_s = torch.zeros(0, p, dtype=torch.float64)
        self.hours = torch.zeros(0, dtype=torch.float64)
        self.steps = torch.zeros(0, dtype=torch.int64)
        self.tracked = torch.zeros(0, dtype=torch.bool)

    # ---- state of one actuator ------------------------------------------------------------------------
    def _row(self, actuator: str) -> int:
        if actuator not in self.rows:
            self.rows[actuator] = len(self.rows)
            p = self.settings.n_particles
            self.k = torch.cat([self.k, torch.zeros(1, p, N_FAULTS, dtype=torch.float64)])
            self.log_s = torch.cat([self.log_s, torch.zeros(1, p, dtype=torch.float64)])
            self.hours = torch.cat([self.hours, torch.zeros(1, dtype=torch.float64)])
            self.steps = torch.cat([self.steps, torch.zeros(1, dtype=torch.int64)])
            self.tracked = torch.cat([self.tracked, torch.zeros(1, dtype=torch.bool)])
        return self.rows[actuator]

    def reserve(self, actuators: Sequence[str]) -> None:
        """Allocate rows for ``actuators`` at once (one concatenation instead of one per actuator)."""
        new = [a for a in dict.fromkeys(actuators) if a not in self.rows]
        if not new:
            return
        p, n = self.settings.n_particles, len(new)
        for a in new:
            self.rows[a] = len(self.rows)
        self.k = torch.cat([self.k, torch.zeros(n, p, N_FAULTS, dtype=torch.float64)])
        self.log_s = torch.cat([self.log_s, torch.zeros(n, p, dtype=torch.float64)])
        self.hours = torch.cat([self.hours, torch.zeros(n, dtype=torch.float64)])
        self.steps = torch.cat([self.steps, torch.zeros(n, dtype=torch.int64)])
        self.tracked = torch.cat([self.tracked, torch.zeros(n, dtype=torch.bool)])

    def state(self, actuator: str) -> dict[str, torch.Tensor]:
        """One actuator's state as tensors (for :mod:`.state`)."""
        r = self.rows[actuator]
        return {"k": self.k[r].clone(), "log_s": self.log_s[r].clone(), "hours": self.hours[r].clone(),
                "steps": self.steps[r].clone(), "tracked": self.tracked[r].clone()}

    def load_state(self, actuator: str, state: dict[str, torch.Tensor]) -> None:
        """Restore one actuator's state written by :meth:`state`."""
        if tuple(state["k"].shape) != tuple(self.k.shape[1:]):
            raise ValueError(f"state of {actuator!r}: particles {tuple(state['k'].shape)}, the tracker has "
                             f"{tuple(self.k.shape[1:])}")
        r = self._row(actuator)
        self.k[r], self.log_s[r] = state["k"], state["log_s"]
        self.hours[r], self.steps[r], self.tracked[r] = state["hours"], state["steps"], state["tracked"]

    # ---- one inspection per actuator of a batch -------------------------------------------------------
    def _normals(self, actuators: Sequence[str], rows: torch.Tensor) -> torch.Tensor:
        """(B, P, 2 D + 9) standard normals, one generator per (actuator, inspection number): [0, 8) eps or the
        initial k, 8 the initial log s, [9, 18) the kernel step, 18 (first particle) the resampling comb, 26 the
        future-eps factor of the RUL."""
        p = self.settings.n_particles
        out = torch.empty(len(actuators), p, 2 * D + N_FAULTS + 1, dtype=torch.float64)
        g = torch.Generator()
        for i, (a, step) in enumerate(zip(actuators, self.steps[rows].tolist())):
            g.manual_seed(actuator_seed(self.settings.seed, a, step))
            out[i] = torch.randn(out.shape[1:], generator=g, dtype=torch.float64)
        return out

    def update(self, actuators: Sequence[str], hours: torch.Tensor, k_hat: torch.Tensor, scale: torch.Tensor,
               fuse: torch.Tensor, faulty: torch.Tensor | None = None, restart: torch.Tensor | None = None
               ) -> Posterior:
        """One inspection of each of ``actuators`` (distinct ids).

        Args:
            hours: (B,) inspection times [h], after the actuator's previous one (the caller checks).
            k_hat: (B, 8) the pipeline's estimates.  scale: (B, 8) their error scales
                (:func:`~.measurement.interval_scale`).
            fuse: (B,) bool, False for an out-of-distribution inspection (predicted, not fused).
            faulty: (B,) bool, the inspection's verdict; a fused faulty one has RUL 5 % = 50 % = 0.
            restart: (B,) bool, maintenance before this inspection: the track starts again.
        """
        if len(set(actuators)) != len(actuators):
            raise ValueError("Tracker.update: one inspection per actuator per call")
        b = len(actuators)
        self.reserve(actuators)
        rows = torch.tensor([self.rows[a] for a in actuators], dtype=torch.long)
        hours = torch.as_tensor(hours, dtype=torch.float64).reshape(b)
        k_hat = torch.as_tensor(k_hat, dtype=torch.float64).reshape(b, N_FAULTS)
        scale = torch.as_tensor(scale, dtype=torch.float64).reshape(b, N_FAULTS)
        fuse = torch.as_tensor(fuse, dtype=torch.bool).reshape(b)
        faulty = torch.zeros(b, dtype=torch.bool) if faulty is None else torch.as_tensor(faulty).bool().reshape(b)
        restart = torch.zeros(b, dtype=torch.bool) if restart is None else torch.as_tensor(restart).bool().reshape(b)
        z = self._normals(actuators, rows)
        k, log_s, tracked = self.k[rows], self.log_s[rows], self.tracked[rows] & ~restart
        cap = math.log(self.settings.max_rate_scale)

        # 2. predict the tracked rows to this inspection
        dt = (hours - self.hours[rows]).clamp(min=0.0)
        if bool(tracked.any()):
            s = log_s.exp()
            k = self._predict(k, s, dt, z[..., :N_FAULTS], tracked)
        # 1. initialise the untracked rows that have a fused inspection
        init = ~tracked & fuse
        if bool(init.any()):
            k0 = reflect_unit(k_hat.unsqueeze(1) + scale.unsqueeze(1) * z[..., :N_FAULTS])
            s0 = (self.law.rate_scale_sigma * z[..., N_FAULTS]).clamp(-cap, cap)
            k = torch.where(init.view(-1, 1, 1), k0, k)
            log_s = torch.where(init.view(-1, 1), s0, log_s)
        # 3. fuse the tracked in-distribution rows
        upd = tracked & fuse
        if bool(upd.any()):
            k, log_s = self._fuse(k, log_s, k_hat, scale, z, upd, cap)
        now_tracked = tracked | init
        self.k[rows], self.log_s[rows], self.tracked[rows] = k, log_s, now_tracked
        self.hours[rows] = torch.where(now_tracked, hours, self.hours[rows])
        self.steps[rows] += 1
        return self._summary(k, log_s, now_tracked, z[:, :, -1], fuse & faulty)

    def _predict(self, k: torch.Tensor, s: torch.Tensor, dt: torch.Tensor, z: torch.Tensor,
                 rows: torch.Tensor) -> torch.Tensor:
        """Particles k (B, P, 8) with rates s (B, P) moved by dt (B,) [h] where ``rows`` (B,) bool."""
        b, p, _ = k.shape
        k0 = self.law.nominal
        tau = (s * dt.unsqueeze(1) * rows.unsqueeze(1)).reshape(-1) / 2.0     # half of each wear-clock step
        half = self.law.propagate((k - k0).reshape(-1, N_FAULTS), tau)
        noise = self.law.noise_std_over(dt * rows).unsqueeze(1) * z              # int eps over dt (B, P, 8)
        moved = self.law.propagate(half + noise.reshape(-1, N_FAULTS), tau)
        return (k0 + moved.reshape(b, p, N_FAULTS)).clamp(0.0, 1.0)

    def _fuse(self, k: torch.Tensor, log_s: torch.Tensor, k_hat: torch.Tensor, scale: torch.Tensor,
              z: torch.Tensor, rows: torch.Tensor, cap: float) -> tuple[torch.Tensor, torch.Tensor]:
        """Weight, resample and move the particles of ``rows`` (B,) bool; the other rows are returned as given."""
        idx = rows.nonzero().flatten()
        kr, sr = k[idx], log_s[idx]
        log_w = log_likelihood(kr, k_hat[idx], scale[idx], self.settings.measurement_dof)
        u = torch.special.ndtr(z[idx, 0, 2 * D])        # one uniform per row for the systematic comb
        anc = systematic_indices(log_w, u)
        x = torch.cat([kr, sr.unsqueeze(-1)], -1).gather(1, anc.unsqueeze(-1).expand(-1, -1, D))
        x = liu_west(x, z[idx, :, D:2 * D], self.settings.shrink)
        k, log_s = k.clone(), log_s.clone()
        k[idx] = x[..., :N_FAULTS].clamp(0.0, 1.0)
        log_s[idx] = x[..., N_FAULTS].clamp(-cap, cap)
        return k, log_s

    def _summary(self, k: torch.Tensor, log_s: torch.Tensor, tracked: torch.Tensor, z_eps: torch.Tensor,
                 faulty: torch.Tensor) -> Posterior:
        b = k.shape[0]
        q = torch.tensor([0.05, 0.95], dtype=torch.float64)
        k_q = torch.quantile(k, q, dim=1)                                           # (2, B, 8)
        s_q = torch.quantile(log_s.exp(), torch.tensor([0.05, 0.5, 0.95], dtype=torch.float64), dim=1).T
        rul = torch.full((b, 3), float("nan"), dtype=torch.float64)
        censored = torch.zeros(b, 3, dtype=torch.bool)
        if self.rul_model is not None and bool(tracked.any()):
            idx = tracked.nonzero().flatten()
            stride = self.settings.n_particles // self.settings.rul_particles
            r, c = self.rul_model(k[idx, ::stride], log_s[idx, ::stride].exp(), z_eps[idx, ::stride])
            rul[idx], censored[idx] = r, c
        # the inspection's verdict says faulty: no life left at 5 and 50 %
        stop = (faulty & tracked).unsqueeze(1) & (torch.arange(3) < 2)
        rul = torch.where(stop, torch.zeros_like(rul), rul)
        censored = censored & ~stop
        nan = ~tracked.view(-1, 1)
        return Posterior(k.mean(1).masked_fill(nan, float("nan")), k_q[0].masked_fill(nan, float("nan")),
                         k_q[1].masked_fill(nan, float("nan")), s_q.masked_fill(nan, float("nan")), rul, censored,
                         tracked.clone())
