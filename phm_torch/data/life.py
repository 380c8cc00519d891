"""Run-to-failure histories: the ``life`` split of ``phm-generate`` (``dataset.life``).

Each actuator starts with a small random damage that the true assessment function phi_a calls healthy
(redrawn otherwise), gets a wear-rate scale s and a rate noise eps from the damage model, and its fault
vector k(t) is integrated with them (:meth:`DamageModel.integrate`). It is inspected every ``every`` hours:
phi_a decides health at each inspection, the end of life (EOL) is the first time phi_a says faulty along
k(t), located on the damage grid between the last healthy and the first faulty inspection and refined
inside its grid step with the exact propagators, and the track stops ``after_eol`` inspections after the
EOL (the first faulty inspection is the first of them). Each inspection is one record of the signal
simulator (the store's fidelity and effects) on the test command, with relative current noise, written
as a measurement CSV (what ``phm-predict`` reads).

The files, the resume and truth.json / index.csv: :mod:`phm_torch.data.life_files`.

Cost: phi_a is batched over every pending actuator (rounds of ``ROUND`` inspections), the records over
actuators (calls of one size, at most ``batch`` records, the last padded: a compiled simulator compiles once).
Every random draw comes from the actuator's own seed stream (seed, index), so an actuator's history does
not depend on the others, on the batching or on interruptions.
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import asdict, dataclass
from typing import Any

import numpy as np
import torch

from ..prognostics.damage import DamageModel
from ..simulator import EMASimulator

log = logging.getLogger(__name__)

ROUND = 16  # inspections assessed per actuator and phi_a round
CANDIDATES = 8  # initial vectors drawn per actuator and round until one is healthy
MAX_DRAW_ROUNDS = 25
REFINE_POINTS, REFINE_LEVELS = 16, 2  # EOL inside its damage-grid step: step / 16^2 resolution


@dataclass(frozen=True)
class LifeSpec:
    """Settings of the life split (``dataset.life``).

    Attributes:
        n_actuators: run-to-failure histories; 0 = no life split.
        every: hours between two inspections [h] (a multiple of the damage model's ``step_hours``).
        initial_damage: largest initial damage per component [k units]: each damage component starts at
            nominal + U(0, initial_damage) away from nominal (toward the inside of [0, 1]; either side for a
            nominal inside); the components the dataset leaves uniform (``dataset.uniform``) are uniform.
        after_eol: inspections at or after the end of life (the first is the first faulty one), >= 1.
        noise: relative current noise: std = noise x the record's RMS current (as ``fdi_band.noise``).
        max_inspections: safety cap per actuator; a history still healthy at the cap is kept, ``eol_hours``
            null and ``censored`` true.
        batch: the most records per simulator call (the calls are of equal size, the last one padded).
        compile: compile the simulator (pays off from a few hundred records; ~1 min once per process).
    """

    n_actuators: int = 0
    every: float = 200.0
    initial_damage: float = 0.01
    after_eol: int = 2
    noise: float = 0.01
    max_inspections: int = 250
    batch: int = 256
    compile: bool = True

    def __post_init__(self) -> None:
        for name, low in (("n_actuators", 0), ("after_eol", 1), ("max_inspections", 2), ("batch", 1)):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int) or v < low:
                raise ValueError(f"dataset.life.{name} must be an integer >= {low}, got {v!r}")
        for name, lo, hi, strict in (
            ("every", 0.0, math.inf, True),
            ("initial_damage", 0.0, 1.0, True),
            ("noise", 0.0, 1.0, False),
        ):
            v = getattr(self, name)
            ok = (
                not isinstance(v, bool)
                and isinstance(v, (int, float))
                and math.isfinite(v)
                and v <= hi
                and (v > lo if strict else v >= lo)
            )
            if not ok:
                raise ValueError(
                    f"dataset.life.{name} must be a number in {'(' if strict else '['}{lo:g}, {hi:g}], got {v!r}"
                )
        if not isinstance(self.compile, bool):
            raise ValueError(f"dataset.life.compile must be true or false, got {self.compile!r}")
        if self.after_eol >= self.max_inspections:
            raise ValueError(
                f"dataset.life.after_eol ({self.after_eol}) must be below dataset.life.max_inspections "
                f"({self.max_inspections})"
            )

    @classmethod
    def of(cls, node: LifeSpec | Mapping[str, Any] | None) -> LifeSpec:
        """A LifeSpec from itself, a mapping of its fields (unknown keys: ValueError) or None (no life split)."""
        if node is None or isinstance(node, LifeSpec):
            return node or cls()
        if not isinstance(node, Mapping):
            raise ValueError(f"dataset.life must map its settings, got {node!r}")
        unknown = sorted(set(node) - set(cls.__dataclass_fields__) - {"_target_"})
        if unknown:
            raise ValueError(f"dataset.life: unknown setting(s) {unknown}; known: {list(cls.__dataclass_fields__)}")
        return cls(**{k: v for k, v in node.items() if k != "_target_"})


def actuator_ids(n: int) -> list[str]:
    """``A000``, ``A001`` ... (wider for more than 1,000)."""
    width = max(3, len(str(n - 1)))
    return [f"A{i:0{width}d}" for i in range(n)]


def _generator(stream: np.random.SeedSequence, *key: int) -> torch.Generator:
    """A torch generator seeded from the child ``key`` of ``stream`` (independent of spawn order)."""
    child = np.random.SeedSequence(stream.entropy, spawn_key=(*stream.spawn_key, *key))
    return torch.Generator().manual_seed(int(child.generate_state(1, np.uint64)[0]))


def near_nominal(
    nominal: torch.Tensor, initial_damage: float, uniform: Sequence[int], n: int, g: torch.Generator
) -> torch.Tensor:
    """n fault vectors (n, 8) float64 near nominal (8,), drawn from generator g: every component within
    ``initial_damage`` of nominal, toward the inside of [0, 1] (either side for a nominal inside), the ``uniform``
    components (0-based) uniform on [0, 1]. How a life history starts, and a damage-law path of the classifier
    refinement (:mod:`phm_torch.surrogates.classifiers.damage_paths`)."""
    nom = nominal.to(torch.float64)
    u = torch.rand(n, nom.numel(), generator=g, dtype=torch.float64)
    side = torch.where(torch.rand(n, nom.numel(), generator=g, dtype=torch.float64) < 0.5, -1.0, 1.0)
    side = torch.where(nom <= 0.0, 1.0, torch.where(nom >= 1.0, -1.0, side))  # inward at a bound
    k = (nom + side * u * initial_damage).clamp(0.0, 1.0)
    phase = torch.rand(n, nom.numel(), generator=g, dtype=torch.float64)
    for i in uniform:
        k[:, i] = phase[:, i]
    return k


class LifeGenerator:
    """Draws, integrates, assesses and simulates the life histories of one config.

    Args:
        life: the settings.   damage: the damage model (its ``rate_scale_sigma`` draws s).
        assess: phi_a, fault vectors (N, 8) -> healthy (N,) bool.
        simulate: fault vectors (B, 8) -> noise-free (time (n,), {"command", "position", "current": (B, n)}).
        stream: the life seed stream (``generation.seed_streams(seed)["life"]``).
        nominal: k0 (8,).   uniform: 0-based components drawn uniform on [0, 1] (the eccentricity phase).
        assess_batch: the most vectors per phi_a call.
    """

    def __init__(
        self,
        life: LifeSpec,
        damage: DamageModel,
        assess: Callable[[torch.Tensor], torch.Tensor],
        simulate: Callable[[torch.Tensor], tuple[torch.Tensor, dict[str, torch.Tensor]]],
        stream: np.random.SeedSequence,
        nominal: Sequence[float],
        uniform: Sequence[int] = (),
        assess_batch: int = 4096,
    ):
        ratio = life.every / damage.step
        if abs(ratio - round(ratio)) > 1e-9:
            raise ValueError(
                f"dataset.life.every ({life.every}) must be a multiple of damage.step_hours "
                f"({damage.step}): inspections lie on the damage grid"
            )
        self.life, self.damage, self.assess_fn, self.simulate = life, damage, assess, simulate
        self.stream, self.uniform = stream, tuple(int(i) for i in uniform)
        self.nominal = torch.as_tensor(nominal, dtype=torch.float64)
        self.per = round(ratio)  # damage-grid steps per inspection interval
        self.assess_batch = int(assess_batch)
        self.timing = {"phi_a_s": 0.0, "integrate_s": 0.0, "simulate_s": 0.0, "write_s": 0.0}
        self.phi_a_vectors = 0

    # ---- physics -------------------------------------------------------------------------------------
    def _assess(self, k: torch.Tensor) -> torch.Tensor:
        """phi_a of fault vectors (N, 8) -> (N,) bool, in batches; k clamped to the unit cube where phi_a is
        defined (damage past 1 only happens on a path already faulty)."""
        t0 = time.perf_counter()
        k = k.clamp(0.0, 1.0)
        out = (
            torch.cat(
                [self.assess_fn(k[i : i + self.assess_batch]).bool() for i in range(0, k.shape[0], self.assess_batch)]
            )
            if k.shape[0]
            else torch.zeros(0, dtype=bool)
        )
        self.timing["phi_a_s"] += time.perf_counter() - t0
        self.phi_a_vectors += k.shape[0]
        return out

    def _candidates(self, g: torch.Generator) -> torch.Tensor:
        """CANDIDATES initial vectors (CANDIDATES, 8) from generator g."""
        return near_nominal(self.nominal, self.life.initial_damage, self.uniform, CANDIDATES, g)

    def initial_states(self, indices: Sequence[int]) -> torch.Tensor:
        """A healthy initial vector per actuator index (P, 8): its first healthy candidate."""
        gens = {i: _generator(self.stream, i, 0) for i in indices}
        chosen: dict[int, torch.Tensor] = {}
        for _ in range(MAX_DRAW_ROUNDS):
            todo = [i for i in indices if i not in chosen]
            if not todo:
                break
            cands = torch.stack([self._candidates(gens[i]) for i in todo])  # (P, C, 8)
            healthy = self._assess(cands.reshape(-1, cands.shape[-1])).view(len(todo), CANDIDATES)
            for row, i in enumerate(todo):
                if healthy[row].any():
                    chosen[i] = cands[row, int(healthy[row].double().argmax())]
        if len(chosen) < len(indices):
            raise ValueError(
                f"dataset.life.initial_damage={self.life.initial_damage!r}: no healthy initial state in "
                f"{MAX_DRAW_ROUNDS * CANDIDATES} draws for some actuator; use a smaller value"
            )
        return torch.stack([chosen[i] for i in indices])

    def histories(self, indices: Sequence[int]) -> list[dict[str, Any]]:
        """The true histories of the actuators ``indices``: initial state, s, k(t) at each inspection,
        phi_a there, EOL. Each dict: ``k0`` (8,), ``rate_scale``, ``eol_hours`` (None: censored),
        ``k`` (n, 8) at the inspections, ``healthy`` (n,) bool, ``hours`` (n,)."""
        if not indices:
            return []
        life, d = self.life, self.damage
        k_init = self.initial_states(indices)
        gens = [_generator(self.stream, i, 1) for i in indices]
        scale = torch.cat([d.sample_rate_scale(1, g) for g in gens])
        span = (life.max_inspections - 1) * life.every
        eps = torch.cat([d.sample_noise(1, g, hours=span) for g in gens])
        t0 = time.perf_counter()
        grid = torch.arange(round(span / d.step) + 1, dtype=torch.float64) * d.step
        traj = d.integrate(k_init, eps, t=grid, scale=scale)  # (T, P, 8)
        self.timing["integrate_s"] += time.perf_counter() - t0
        n_p, cap = len(indices), life.max_inspections
        health = torch.ones(n_p, cap, dtype=torch.bool)
        done = torch.zeros(n_p, dtype=torch.long)  # inspections assessed so far
        first = torch.full((n_p,), -1, dtype=torch.long)  # first faulty inspection (-1: none yet)
        while True:
            need = torch.where(first >= 0, (first + life.after_eol).clamp(max=cap), torch.full_like(first, cap))
            active = (done < need).nonzero().flatten().tolist()
            if not active:
                break
            rows, cols = [], []
            for p in active:
                j = list(range(int(done[p]), min(int(done[p]) + ROUND, cap)))
                rows += [p] * len(j)
                cols += j
            rows_t, cols_t = torch.tensor(rows), torch.tensor(cols)
            health[rows_t, cols_t] = self._assess(traj[cols_t * self.per, rows_t])
            for p in active:
                done[p] = min(int(done[p]) + ROUND, cap)
                if first[p] < 0 and not health[p, : done[p]].all():
                    first[p] = int((~health[p, : done[p]]).double().argmax())
            # phi_a along the paths comes before any record is simulated and takes minutes: say how far it is
            log.info(
                "life: phi_a at %d inspections of %d actuators, %d of them past their first faulty one",
                int(done.sum()),
                n_p,
                int((first >= 0).sum()),
            )
        eol = self._locate_eol(traj, first, eps, scale)
        out = []
        for p, _ in enumerate(indices):
            n = int(min(int(first[p]) + life.after_eol, cap)) if first[p] >= 0 else cap
            j = torch.arange(n)
            out.append(
                {
                    "k0": k_init[p],
                    "rate_scale": float(scale[p]),
                    "hours": (j * life.every).double(),
                    "k": traj[j * self.per, p].clamp(0.0, 1.0),
                    "healthy": health[p, :n],
                    "eol_hours": float(eol[p]) if first[p] >= 0 else None,
                }
            )
        return out

    def _locate_eol(
        self, traj: torch.Tensor, first: torch.Tensor, eps: torch.Tensor, scale: torch.Tensor
    ) -> torch.Tensor:
        """EOL [h] (P,) of the actuators with a faulty inspection ``first`` (others: NaN): the first faulty
        damage-grid point after the last healthy inspection, refined inside its step."""
        d = self.damage
        eol = torch.full((first.numel(),), float("nan"), dtype=torch.float64)
        found = (first > 0).nonzero().flatten()  # first == 0 cannot happen: the start is healthy
        if not found.numel():
            return eol
        lo = (first[found] - 1) * self.per  # last healthy inspection's grid index
        g = first[found] * self.per  # first faulty inspection's grid index
        if self.per > 1:  # grid points between the two inspections
            offs = torch.arange(1, self.per)
            idx = lo.unsqueeze(1) + offs  # (n, per - 1)
            bad = ~self._assess(traj[idx, found.unsqueeze(1)].reshape(-1, traj.shape[-1])).view(idx.shape)
            hit = bad.any(1)
            g = torch.where(hit, idx.gather(1, bad.double().argmax(1, keepdim=True)).squeeze(1), g)
        start = traj[g - 1, found]  # last healthy grid state (n, 8)
        t_start = (g - 1).double() * d.step
        block = torch.clamp((t_start / d.block).floor().long(), max=eps.shape[1] - 1)
        rate_eps, s = eps[found, block], scale[found]  # constant over the step
        a_lo, width = torch.zeros(found.numel(), dtype=torch.float64), d.step
        frac = torch.arange(1, REFINE_POINTS + 1, dtype=torch.float64) / REFINE_POINTS
        for _ in range(REFINE_LEVELS):
            tau = a_lo.unsqueeze(1) + width * frac  # (n, M)
            k = self._advance(start, tau, rate_eps, s)  # (n, M, 8)
            bad = ~self._assess(k.reshape(-1, k.shape[-1])).view(tau.shape)
            bad[:, -1] |= width == d.step  # the grid point itself is faulty (RK4 vs exact: ~1e-12 apart)
            m = torch.where(bad.any(1), bad.double().argmax(1), torch.full_like(a_lo, REFINE_POINTS - 1).long())
            a_lo = a_lo + width * m.double() / REFINE_POINTS
            width = width / REFINE_POINTS
        eol[found] = t_start + a_lo + width  # the first faulty sub-point
        return eol

    def _advance(self, k: torch.Tensor, tau: torch.Tensor, rate_eps: torch.Tensor, s: torch.Tensor) -> torch.Tensor:
        """Exact k(tau) (n, M, 8) from k (n, 8) with constant eps (n, 8) and scale s (n,): the clock change
        A_s(tau) = A(s tau), B_s(tau) = B(s tau) / s of :meth:`DamageModel.transitions`."""
        a, b = self.damage.transitions((s.unsqueeze(1) * tau).reshape(-1))
        n, m = tau.shape
        a, b = a.view(n, m, 8, 8), b.view(n, m, 8, 8)
        dk = (k - self.nominal).unsqueeze(1).unsqueeze(-1)  # (n, 1, 8, 1)
        e = (rate_eps / s.unsqueeze(1)).unsqueeze(1).unsqueeze(-1)
        return self.nominal + (a @ dk + b @ e).squeeze(-1)

    # ---- records -------------------------------------------------------------------------------------
    def records(self, index: int, time_s: torch.Tensor, signals: Mapping[str, torch.Tensor]) -> dict[str, np.ndarray]:
        """Noisy measurement channels (n, e) of one actuator from its noise-free ``signals`` (n, e)."""
        g = _generator(self.stream, index, 2)
        cur = signals["current"].double()
        rms = torch.linalg.vector_norm(cur, dim=-1, keepdim=True) / cur.shape[-1] ** 0.5
        noisy = cur + self.life.noise * rms * torch.randn(cur.shape, generator=g, dtype=torch.float64)
        return {
            "time": time_s.double().numpy(),
            "command": signals["command"].double().numpy(),
            "position": signals["position"].double().numpy(),
            "current": noisy.numpy(),
        }


def settings_record(life: LifeSpec) -> dict[str, Any]:
    """The life settings as recorded in truth.json."""
    return asdict(life)


def simulator(
    params: Any,
    fidelity: str,
    substeps: int | None,
    effects: Mapping[str, Any],
    compile: bool,
    command: Callable[[torch.Tensor], torch.Tensor],
    duration: float,
    device: str | torch.device = "cpu",
) -> Callable[[torch.Tensor], tuple[torch.Tensor, dict[str, torch.Tensor]]]:
    """The records' simulator: fault vectors (B, 8) -> (time (n,) [s], noise-free channels (B, n))."""
    sim = EMASimulator(params, fidelity, substeps=substeps, device=device, compile=compile, effects=effects)

    def run(k: torch.Tensor) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
        with torch.no_grad():
            sig = sim.run(k, command, duration, channels=["position", "current"], out_dtype=torch.float32)
        return sig.time.cpu(), {c: sig[c].cpu() for c in ("command", "position", "current")}

    return run
