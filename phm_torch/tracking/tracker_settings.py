"""The tracker's settings (the ``tracker`` node of conf/track.yaml): particles, seeds, the end-of-life rule, the
measurement's tails, the priors of the wear-rate scale and of what the FDI does not identify."""

from __future__ import annotations

import math
from dataclasses import dataclass

from ..data.life import LifeSpec

FAULTY_AT = {"p5": 0, "p50": 1}  # TrackerSettings.faulty_at: its column in the RUL quantiles (5, 50, 95 %)


@dataclass
class TrackerSettings:
    """Settings of the tracker (the ``tracker`` node of conf/track.yaml).

    Args:
        n_particles: particles per actuator.
        rul_particles: particles (the first this many, weighted) whose RUL makes the 5/50/95 % band.
        seed: base seed of the per-(actuator, inspection) generators.
        measurement_dof: degrees of freedom of the Student-t whose 90 % interval is the calibrated one; the
            Kalman filters read its scale as a Gaussian's (inf: the Gaussian of that interval).
        shrink: Liu-West a in (0, 1] (1: no kernel step).
        max_rate_scale: the particles' s stays within [1 / this, this].
        bisections: halvings of the RUL crossing interval (cold search).
        resample_ess: resample when the effective sample size is below this fraction of n_particles.
        verdict: ``posterior``: an inspection is faulty where the posterior's median RUL is 0; ``record``: also
            where the record's own verdict (phm-predict's) is faulty, whose RUL 5 % and 50 % are then 0.
        verdict_evidence: weigh the RUL particles already faulty by the record's P(faulty) as a likelihood ratio
            (:func:`~.measurement.verdict_odds`; needs the pipeline's ``verdict_prior_faulty``).
        faulty_at: the posterior RUL quantile whose reaching 0 makes an inspection faulty: ``p50`` (most of the
            probability past the health boundary) or ``p5`` (5 % of it: an earlier flag, fewer ends of life flagged
            late); a faulty inspection's RUL 5 % and 50 % are 0, as where the record's own verdict decides.
        new_spread: [k units] the largest deviation of a new actuator's damage from nominal (the life histories'
            ``initial_damage``): the prior of a component the FDI does not identify, grown by the damage law from new
            (:func:`~.kalman.from_nominal`).
        boundary_std_hours: [h] the health classifier's timing error against phi_a where a damage path crosses the
            boundary, given to each healthy RUL particle (:class:`~.particle_rul.ParticleRUL`). 60: the std measured
            along 60 histories of the reference actuator (50-69 h; docs/prognostics.md); 0: none.
    """

    n_particles: int = 128
    rul_particles: int = 64
    seed: int = 0
    measurement_dof: float = math.inf
    shrink: float = 0.9
    max_rate_scale: float = 8.0
    bisections: int = 6
    resample_ess: float = 0.5
    verdict: str = "record"
    verdict_evidence: bool = True
    faulty_at: str = "p50"
    boundary_std_hours: float = 60.0
    new_spread: float = LifeSpec.initial_damage

    def __post_init__(self) -> None:
        for name in ("n_particles", "rul_particles", "seed", "bisections"):
            value = getattr(self, name)
            if (
                isinstance(value, bool)
                or not isinstance(value, int)
                or value < (0 if name in ("seed", "bisections") else 2)
            ):
                raise ValueError(
                    f"tracker.{name} must be an integer >= {0 if name in ('seed', 'bisections') else 2}, got {value!r}"
                )
        if self.rul_particles > self.n_particles:
            raise ValueError(
                f"tracker.rul_particles ({self.rul_particles}) must be <= tracker.n_particles ({self.n_particles})"
            )
        if not 0.0 <= float(self.resample_ess) <= 1.0:
            raise ValueError(f"tracker.resample_ess must be in [0, 1], got {self.resample_ess!r}")
        if self.verdict not in ("posterior", "record"):
            raise ValueError(f"tracker.verdict must be 'posterior' or 'record', got {self.verdict!r}")
        if self.faulty_at not in FAULTY_AT:
            raise ValueError(f"tracker.faulty_at must be one of {list(FAULTY_AT)}, got {self.faulty_at!r}")
        self.measurement_dof = float(self.measurement_dof)
        if not self.measurement_dof > 0:
            raise ValueError(f"tracker.measurement_dof must be > 0 (inf: Gaussian), got {self.measurement_dof!r}")
        if not 0.0 < float(self.shrink) <= 1.0:
            raise ValueError(f"tracker.shrink must be in (0, 1], got {self.shrink!r}")
        if not float(self.max_rate_scale) > 1.0:
            raise ValueError(f"tracker.max_rate_scale must be > 1, got {self.max_rate_scale!r}")
        self.new_spread = float(self.new_spread)
        if not 0.0 <= self.new_spread <= 1.0:
            raise ValueError(f"tracker.new_spread must be in [0, 1], got {self.new_spread!r}")
        self.boundary_std_hours = float(self.boundary_std_hours)
        if not (math.isfinite(self.boundary_std_hours) and self.boundary_std_hours >= 0.0):
            raise ValueError(f"tracker.boundary_std_hours must be finite and >= 0, got {self.boundary_std_hours!r}")
