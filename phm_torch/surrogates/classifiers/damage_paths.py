"""Candidates on the damage law's paths: where the health classifier's boundary is crossed in service.

The health classifier is the RUL's stopping event: the prognosis integrates dk/dt = s F (k - k0) + eps from an
estimate until f(k) = 0. Its boundary matters most where those paths cross it, and importance-sampled vectors
are thin there. Refined on importance-sampled candidates only, the classifier of the reference actuator crossed
phi_a's boundary a median 70 h late (std 90-110 h) along 60 simulated run-to-failure paths; refined with points
of such paths as well, 1-21 h (std 60-80 h), and the first inspection it calls faulty was phi_a's for 45 of 60
actuators instead of 28 (docs/surrogates.md, "Boundary refinement").

A path starts as a life history does (:func:`phm_torch.data.life.near_nominal`): every damage component within
``initial_damage`` of nominal (toward the inside of [0, 1]), the ``uniform`` components (the eccentricity phase)
uniform; it gets a wear-rate scale s and block-constant eps from the damage model and is integrated on the
damage grid over the model's horizon. Each path gives ``POINTS_PER_PATH`` candidates at grid times drawn
uniformly (clamped to the unit cube, where phi_a is defined): many paths with a few points each, so that the
candidates a round keeps (the least sure) spread over many crossings.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
import torch

from ...data.life import near_nominal
from ...prognostics.damage import DamageModel

POINTS_PER_PATH = 16
PATHS_PER_BATCH = 2048  # paths integrated at once: (T, 2048, 8) float64 is 53 MB on a 401-point grid


class DamagePathSampler:
    """Points on damage-law paths from near-nominal initial states.

    Args:
        damage: the damage law (its rate, eps, s spread, grid and horizon).
        initial_damage: largest initial distance from nominal per damage component [k units], > 0.
        uniform: 0-based components drawn uniform on [0, 1] at the start (constant along the path).
        seed: base seed; ``sample(n, r)`` is deterministic in (seed, r).
    """

    def __init__(self, damage: DamageModel, initial_damage: float, uniform: Sequence[int] = (), seed: int = 0):
        if not (isinstance(initial_damage, (int, float)) and math.isfinite(initial_damage) and initial_damage > 0):
            raise ValueError(f"initial_damage must be a number > 0, got {initial_damage!r}")
        self.damage, self.initial_damage = damage, float(initial_damage)
        self.uniform, self.seed = tuple(int(i) for i in uniform), int(seed)

    def paths(self, n_paths: int, g: torch.Generator) -> torch.Tensor:
        """k(t) of ``n_paths`` paths on the damage grid, (T, n_paths, 8), clamped to [0, 1]."""
        d = self.damage
        k = near_nominal(d.nominal, self.initial_damage, self.uniform, n_paths, g)
        scale = d.sample_rate_scale(n_paths, g)
        eps = d.sample_noise(n_paths, g)
        return d.integrate(k, eps, t=d.grid, scale=scale).clamp(0.0, 1.0)

    def sample(self, n: int, r: int) -> np.ndarray:
        """n candidates (n, 8) float64 of round r (deterministic in (seed, r))."""
        if n < 1:
            raise ValueError(f"n must be >= 1, got {n!r}")
        g = torch.Generator().manual_seed(int(np.random.SeedSequence([self.seed, r]).generate_state(1)[0]))
        n_paths = math.ceil(n / POINTS_PER_PATH)
        out = []
        for start in range(0, n_paths, PATHS_PER_BATCH):
            b = min(PATHS_PER_BATCH, n_paths - start)
            traj = self.paths(b, g)  # (T, b, 8)
            t = torch.randint(0, traj.shape[0], (b, POINTS_PER_PATH), generator=g)
            out.append(traj[t, torch.arange(b).unsqueeze(1)].reshape(-1, traj.shape[-1]))
        return torch.cat(out)[:n].numpy()
