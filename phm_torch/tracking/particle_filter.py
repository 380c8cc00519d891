"""Particle filter over the wear-rate scale s per actuator, with a Kalman filter over k inside each particle
(Rao-Blackwellised), batched in torch across particles and actuators.

State of one actuator: P weighted particles, each a log wear-rate scale log s, the Gaussian of k given that s
(mean (8,), covariance (8, 8); :mod:`.kalman`), the standard normals that draw its RUL sample of k, and its last
wear-clock crossing (the warm start of its RUL search). One inspection at hours h with the pipeline's estimate
k_hat and its error scale:

1. *initialise* (first fused inspection of a track, or a ``restart`` after maintenance): log s ~ N(0, sigma_s^2)
   (the fleet prior of the damage law), k ~ N(k_hat, scale^2) for every particle, equal weights;
2. *predict* from the previous inspection (dt = h - h_prev): each particle's Kalman filter with the exact
   expm(s F dt) of its own s and the variance of the block-constant eps (:class:`~.damage_law.DamageLaw`);
3. *update* (in-distribution inspections only; an OOD one stops after the prediction, ``fused`` false): each
   particle's Kalman update, its weight times its marginal likelihood of k_hat; only when the effective sample
   size falls below ``resample_ess`` x P, systematic resampling and a Liu-West kernel step on log s
   (:mod:`.resampling`), held within +/- log(max_rate_scale). Sampling k as well (the first version) made the
   weights degenerate on 8 precisely measured components; s alone is one dimension and keeps its spread;
4. *summarise*: weighted 5/50/95 % of s; k's mean and 5/95 % from one sample of k per particle; the RUL band
   from the first ``rul_particles`` particles' samples, weighted (after a resampling the copies whose
   ancestor has a known crossing are put there first, in random order: the particles are exchangeable, so
   the subset stays a random sample of the cloud).

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

from ..faults import N_FAULTS
from . import kalman
from .damage_law import DamageLaw
from .particle_rul import HUGE, ParticleRUL, weighted_quantiles
from .resampling import liu_west, systematic_indices
from .response import FDIResponse
from .tracker_settings import FAULTY_AT, TrackerSettings


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
        verdict_prior: the fault rate at which the pipeline's P(faulty) was calibrated (metadata
            ``verdict_prior_faulty``); None, or ``settings.verdict_evidence`` false: the records' verdicts weigh nothing.
        response: the FDI's response near nominal (:class:`~.response.FDIResponse`), inverted before each k_hat
            is fused (:func:`~.fleet.track_fleet`); None: k_hat read as centred on k.
        not_identified: the components the pipeline's k_hat does not measure (its training prior), which
            :func:`~.fleet.track_fleet` does not fuse (:meth:`update`'s ``observed``).

    State per actuator id, rows of: ``k`` (A, P, 8) and ``k_cov`` (A, P, 8, 8) the Gaussian of k per particle,
    ``log_s`` (A, P), ``log_w`` (A, P) normalised log weights, ``z_k`` (A, P, 8) the normals of each particle's
    RUL sample of k, ``tau`` (A, P) [h] last wear-clock crossings (NaN: unknown), ``hours`` (A,) [h], ``steps``
    (A,) inspections seen, ``tracked`` (A,) bool; :meth:`state` / :meth:`load_state` move one actuator's in and out.
    """

    FIELDS = ("k", "k_cov", "log_s", "log_w", "z_k", "tau", "hours", "steps", "tracked")
    PARTICLE_FIELDS = ("k", "k_cov", "log_s", "log_w", "z_k", "tau")

    def __init__(
        self,
        law: DamageLaw,
        rul: ParticleRUL | None,
        settings: TrackerSettings | None = None,
        verdict_prior: float | None = None,
        response: FDIResponse | None = None,
        not_identified: Sequence[str] = (),
    ):
        self.law, self.rul_model, self.response = law, rul, response
        self.not_identified = list(not_identified)
        self.settings = settings or TrackerSettings()
        # the fault rate P(faulty) was calibrated at (None: the record's verdict is not weighed)
        self.verdict_prior = verdict_prior if self.settings.verdict_evidence else None
        self.rows: dict[str, int] = {}
        for name, value in self._blank(0).items():
            setattr(self, name, value)

    def _blank(self, n: int) -> dict[str, torch.Tensor]:
        p, f64 = self.settings.n_particles, torch.float64
        return {
            "k": torch.zeros(n, p, N_FAULTS, dtype=f64),
            "k_cov": torch.zeros(n, p, N_FAULTS, N_FAULTS, dtype=f64),
            "log_s": torch.zeros(n, p, dtype=f64),
            "log_w": torch.full((n, p), -math.log(p), dtype=f64),
            "z_k": torch.zeros(n, p, N_FAULTS, dtype=f64),
            "tau": torch.full((n, p), float("nan"), dtype=f64),
            "hours": torch.zeros(n, dtype=f64),
            "steps": torch.zeros(n, dtype=torch.int64),
            "tracked": torch.zeros(n, dtype=torch.bool),
        }

    # ---- state of one actuator ------------------------------------------------------------------------
    def reserve(self, actuators: Sequence[str]) -> None:
        """Allocate rows for ``actuators`` at once (one concatenation instead of one per actuator)."""
        new = [a for a in dict.fromkeys(actuators) if a not in self.rows]
        if not new:
            return
        for a in new:
            self.rows[a] = len(self.rows)
        for name, value in self._blank(len(new)).items():
            setattr(self, name, torch.cat([getattr(self, name), value]))

    def state(self, actuator: str) -> dict[str, torch.Tensor]:
        """One actuator's state as tensors (for :mod:`.state`)."""
        r = self.rows[actuator]
        return {name: getattr(self, name)[r].clone() for name in self.FIELDS}

    def load_state(self, actuator: str, state: dict[str, torch.Tensor]) -> None:
        """Restore one actuator's state written by :meth:`state`."""
        if tuple(state["k"].shape) != tuple(self.k.shape[1:]) or set(state) != set(self.FIELDS):
            raise ValueError(
                f"state of {actuator!r}: particles {tuple(state['k'].shape)} with {sorted(state)}, the "
                f"tracker has {tuple(self.k.shape[1:])} with {sorted(self.FIELDS)}"
            )
        self.reserve([actuator])
        r = self.rows[actuator]
        for name in self.FIELDS:
            getattr(self, name)[r] = state[name]

    # ---- one inspection per actuator of a batch -------------------------------------------------------
    def _normals(self, actuators: Sequence[str], rows: torch.Tensor) -> torch.Tensor:
        """(B, P, 14) standard normals, one generator per (actuator, inspection number): [0, 8) the RUL sample's
        normals of a new track, 8 the initial log s, 9 the kernel step, 10 (first particle) the resampling comb,
        11 the future-eps factor of the RUL, 12 the order of the resampled copies, 13 the health boundary's timing
        error of the RUL (drawn after the others, so that they are those of a generator without it)."""
        p = self.settings.n_particles
        out = torch.empty(len(actuators), p, N_FAULTS + 6, dtype=torch.float64)
        g = torch.Generator()
        for i, (a, step) in enumerate(zip(actuators, self.steps[rows].tolist())):
            g.manual_seed(actuator_seed(self.settings.seed, a, step))
            out[i, :, : N_FAULTS + 5] = torch.randn((p, N_FAULTS + 5), generator=g, dtype=torch.float64)
            out[i, :, N_FAULTS + 5] = torch.randn(p, generator=g, dtype=torch.float64)
        return out

    def update(
        self,
        actuators: Sequence[str],
        hours: torch.Tensor,
        k_hat: torch.Tensor,
        scale: torch.Tensor,
        fuse: torch.Tensor,
        faulty: torch.Tensor | None = None,
        restart: torch.Tensor | None = None,
        faulty_odds: torch.Tensor | None = None,
        observed: torch.Tensor | None = None,
    ) -> Posterior:
        """One inspection of each of ``actuators`` (distinct ids).

        Args:
            hours: (B,) inspection times [h], after the actuator's previous one (the caller checks).
            k_hat: (B, 8) the pipeline's estimates.  scale: (B, 8) their error scales
                (:func:`~.measurement.interval_scale`).
            fuse: (B,) bool, False for an out-of-distribution inspection (predicted, not fused).
            faulty: (B,) bool, the inspection's verdict; a fused faulty one has RUL 5 % = 50 % = 0.
            restart: (B,) bool, maintenance before this inspection: the track starts again.
            observed: (B, 8) bool, the components k_hat measures (None: all). An unread one (its estimate is the
                training prior: phm-evaluate's R^2 below 0.25) is not fused: it starts at the law's prediction from
                new over the inspection's hours (from nominal at a restart; :func:`~.kalman.from_nominal`) and
                follows the law, since fusing a prior mean as a reading pulls k there with a confidence that grows
                with every inspection.
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
        if observed is not None:
            observed = torch.as_tensor(observed).bool().reshape(b, N_FAULTS)
        z = self._normals(actuators, rows)
        st = {name: getattr(self, name)[rows] for name in self.PARTICLE_FIELDS}
        tracked = self.tracked[rows] & ~restart
        cap = math.log(self.settings.max_rate_scale)

        # 2. predict the tracked rows to this inspection; the crossings move by the wear clock s dt
        if bool(tracked.any()):
            i = tracked.nonzero().flatten()
            s, dt = st["log_s"][i].exp(), (hours[i] - self.hours[rows[i]]).clamp(min=0.0)
            st["k"][i], st["k_cov"][i] = kalman.predict(self.law, st["k"][i], st["k_cov"][i], s, dt)
            tau = st["tau"][i]
            st["tau"][i] = torch.where(tau >= HUGE, tau, tau - s * dt.unsqueeze(1))
        # 1. initialise the untracked rows that have a fused inspection
        init = ~tracked & fuse
        if bool(init.any()):
            i = init.nonzero().flatten()
            p = st["log_s"].shape[1]
            st["log_s"][i] = (self.law.rate_scale_sigma * z[i, :, N_FAULTS]).clamp(-cap, cap)
            seen = None if observed is None else observed[i]
            prior = None
            if seen is not None and not bool(seen.all()):
                since_new = torch.where(restart[i], torch.zeros_like(hours[i]), hours[i])
                prior = kalman.from_nominal(self.law, st["log_s"][i].exp(), since_new, self.settings.new_spread)
            st["k"][i], st["k_cov"][i] = kalman.start(k_hat[i], scale[i], p, seen, prior)
            st["log_w"][i] = -math.log(p)
            st["z_k"][i] = z[i, :, :N_FAULTS]
            st["tau"][i] = float("nan")
        # 3. fuse the tracked in-distribution rows
        upd = tracked & fuse
        if bool(upd.any()):
            self._fuse(st, k_hat, scale, z, upd, cap, observed)
        now_tracked = tracked | init
        odds = None if faulty_odds is None else torch.where(fuse, torch.as_tensor(faulty_odds).reshape(b), 1.0)
        post = self._summary(st, now_tracked, z[:, :, N_FAULTS + 3], fuse & faulty, odds, z[:, :, N_FAULTS + 5])
        for name, value in st.items():
            getattr(self, name)[rows] = value
        self.tracked[rows] = now_tracked
        self.hours[rows] = torch.where(now_tracked, hours, self.hours[rows])
        self.steps[rows] += 1
        return post

    def _fuse(
        self,
        st: dict[str, torch.Tensor],
        k_hat: torch.Tensor,
        scale: torch.Tensor,
        z: torch.Tensor,
        rows: torch.Tensor,
        cap: float,
        observed: torch.Tensor | None = None,
    ) -> None:
        """Kalman-update (the ``observed`` (B, 8) components, None: all) and reweight the particles of ``rows`` (B,)
        bool in ``st`` (in place); resample and move those whose ESS fell below the threshold."""
        idx = rows.nonzero().flatten()
        seen = None if observed is None else observed[idx]
        st["k"][idx], st["k_cov"][idx], loglik = kalman.update(
            st["k"][idx], st["k_cov"][idx], k_hat[idx], scale[idx], seen
        )
        log_w = st["log_w"][idx] + loglik
        log_w = log_w - torch.logsumexp(log_w, dim=1, keepdim=True)
        st["log_w"][idx] = log_w
        ess = 1.0 / torch.exp(2.0 * log_w).sum(1)
        low = ess < self.settings.resample_ess * log_w.shape[1]
        if not bool(low.any()):
            return
        idx, log_w = idx[low], log_w[low]
        p = log_w.shape[1]
        u = torch.special.ndtr(z[idx, 0, N_FAULTS + 2])  # one uniform per row for the systematic comb
        anc = systematic_indices(log_w, u)
        # the copies are exchangeable: put those whose ancestor has a known crossing first (random order), so
        # the RUL subset (the first rul_particles) keeps its warm starts
        known = torch.isfinite(st["tau"][idx].gather(1, anc))
        key = torch.special.ndtr(z[idx, :, N_FAULTS + 4]) - known.to(torch.float64)
        anc = anc.gather(1, torch.argsort(key, dim=1))
        for name in self.PARTICLE_FIELDS:
            v = st[name][idx]
            shape = anc.shape + (1,) * (v.dim() - 2)
            st[name][idx] = v.gather(1, anc.reshape(shape).expand_as(v))
        log_s = liu_west(st["log_s"][idx].unsqueeze(-1), z[idx, :, N_FAULTS + 1 : N_FAULTS + 2], self.settings.shrink)
        st["log_s"][idx] = log_s.squeeze(-1).clamp(-cap, cap)
        st["log_w"][idx] = -math.log(p)

    def _summary(
        self,
        st: dict[str, torch.Tensor],
        tracked: torch.Tensor,
        z_eps: torch.Tensor,
        faulty: torch.Tensor,
        faulty_odds: torch.Tensor | None = None,
        z_boundary: torch.Tensor | None = None,
    ) -> Posterior:
        """Weighted summaries of the batch; refreshes ``st["tau"]`` of the RUL subset."""
        k_mean_p, log_s = st["k"], st["log_s"]
        b = k_mean_p.shape[0]
        w = torch.softmax(st["log_w"], dim=1)
        k = kalman.sample(k_mean_p, st["k_cov"], st["z_k"]).clamp(0.0, 1.0)  # one k per particle
        k_q = weighted_quantiles(k, w, (0.05, 0.95))  # (B, 2, 8)
        s_q = weighted_quantiles(log_s.exp(), w, (0.05, 0.5, 0.95))  # (B, 3)
        rul = torch.full((b, 3), float("nan"), dtype=torch.float64)
        censored = torch.zeros(b, 3, dtype=torch.bool)
        if self.rul_model is not None and bool(tracked.any()):
            idx = tracked.nonzero().flatten()
            m = min(self.settings.rul_particles, k.shape[1])
            wm = w[idx, :m] / w[idx, :m].sum(1, keepdim=True)
            odds = None if faulty_odds is None else faulty_odds[idx]
            zb = None if z_boundary is None else z_boundary[idx, :m]
            r, c, tau = self.rul_model(
                k[idx, :m], log_s[idx, :m].exp(), z_eps[idx, :m], wm, st["tau"][idx, :m], odds, zb
            )
            rul[idx], censored[idx] = r, c
            st["tau"][idx, :m] = tau
        # the inspection's verdict says faulty, or the posterior's faulty_at quantile is already 0: no life left at 5
        # and 50 % (the 5 % quantile is 0 wherever the 50 % is)
        past = rul[:, FAULTY_AT[self.settings.faulty_at]] <= 0.0  # NaN (untracked): False
        stop = ((faulty | past) & tracked).unsqueeze(1) & (torch.arange(3) < 2)
        rul = torch.where(stop, torch.zeros_like(rul), rul)
        censored = censored & ~stop
        nan = ~tracked.view(-1, 1)
        k_mean = (w.unsqueeze(-1) * k_mean_p).sum(1).clamp(0.0, 1.0)
        return Posterior(
            k_mean.masked_fill(nan, float("nan")),
            k_q[:, 0].masked_fill(nan, float("nan")),
            k_q[:, 1].masked_fill(nan, float("nan")),
            s_q.masked_fill(nan, float("nan")),
            rul,
            censored,
            tracked.clone(),
        )
