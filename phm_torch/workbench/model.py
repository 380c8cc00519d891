"""Batched evaluation of many models on the measured records: one simulator call per record length.

A *block* is a :class:`ParameterSpace` with a batch X (P, n) of its parameter vectors. Blocks of different
models (different effects, the neural closure) share one simulator holding the union of their effects:
an effect missing from a block's model has its strength parameters at exactly 0 in that block's rows,
which the effect library guarantees leaves the model unchanged. Records of equal length run in the same
call (their commands as a (B, n) tensor); the batch is settings x records, record-major.
"""

from __future__ import annotations

from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass

import torch

from ..effects import EFFECTS, Effect
from ..params import ActuatorParams
from ..simulator import MOTORS, SHARED_CHANNELS, EMASimulator
from .closure_net import NeuralClosure
from .data import Record
from .parameters import ParameterSpace, effect_defaults

STATE_CHANNELS = SHARED_CHANNELS  # every fidelity records them


@contextmanager
def threads(n: int | None) -> Iterator[None]:
    """Run with ``n`` intra-op threads (``None``: unchanged), restoring the previous number afterwards.

    The simulator's tensors are small (B,) vectors; transcendental ops on a few hundred elements still go
    parallel, and on a shared 2-core host each such call then waits for a busy thread: a 96-row LF run was
    measured 18x slower with 2 threads than with 1.
    """
    if n is None:
        yield
        return
    old = torch.get_num_threads()
    torch.set_num_threads(n)
    try:
        yield
    finally:
        torch.set_num_threads(old)


@dataclass
class BlockOutput:
    """Simulation of one block: ``channels[r][c]`` is (P, n_r) for record r and channel c."""

    channels: list[dict[str, torch.Tensor]]

    def row(self, i: int) -> list[dict[str, torch.Tensor]]:
        """The simulated channels of row i, per record ({channel: (n_r,)})."""
        return [{c: v[i] for c, v in rec.items()} for rec in self.channels]


class Evaluator:
    """Simulates blocks of parameter vectors on the records and forms normalised residuals.

    Args:
        params: the datasheet.  fidelity: ``"lf"`` or ``"hf"``.  records: the measurements.
        channels: compared channels.  device: simulation device.
        threads: intra-op threads during simulations (see :func:`threads`; ``None`` leaves torch's setting).
    """

    def __init__(
        self,
        params: ActuatorParams,
        fidelity: str,
        records: Sequence[Record],
        channels: Sequence[str],
        device: str | torch.device = "cpu",
        threads: int | None = 1,
    ):
        if not records:
            raise ValueError("the workbench needs at least one measurement record")
        self.params, self.fidelity, self.records = params, fidelity, list(records)
        self.channels = tuple(channels)
        self.device = torch.device(device)
        if fidelity not in MOTORS:
            raise ValueError(f"fidelity must be one of {sorted(MOTORS)}, got {fidelity!r}")
        # a motor's own channels (the HF phase currents) exist in that fidelity only
        theirs = [
            c
            for c in self.channels
            if c not in SHARED_CHANNELS
            and c not in MOTORS[fidelity].channels
            and any(c in m.channels for m in MOTORS.values())
        ]
        if theirs:
            owners = sorted(f for f, m in MOTORS.items() if set(theirs) & set(m.channels))
            raise ValueError(
                f"channels {theirs} exist only in the {'/'.join(f.upper() for f in owners)} model; "
                f"use fidelity={owners[0]} or drop them"
            )
        self.sim_channels = tuple(dict.fromkeys((*STATE_CHANNELS, *self.channels)))
        groups: dict[int, list[int]] = {}
        for i, rec in enumerate(self.records):
            groups.setdefault(len(rec), []).append(i)
        self.groups = list(groups.values())
        self.calls = 0
        self.simulated_rows = 0
        if threads is not None and threads < 1:
            raise ValueError(f"threads must be >= 1 or null, got {threads!r}")
        self.threads = threads

    @property
    def m(self) -> int:
        """Length of a residual vector: samples x channels summed over records."""
        return sum(len(r) for r in self.records) * len(self.channels)

    def simulate(self, blocks: Sequence[tuple[ParameterSpace, torch.Tensor]]) -> list[BlockOutput]:
        """Run every block in one simulator call per record length.

        Args:
            blocks: [(space, X (P_j, n_j))].
        Returns:
            One :class:`BlockOutput` per block.
        """
        sizes = [int(x.shape[0]) for _, x in blocks]
        total = sum(sizes)
        faults, scales, effects, closures = [], {}, {}, []
        names: list[str] = []
        for space, _ in blocks:
            names += [n for n in space.effects if n not in names]
        closure_net = next((s.closure for s, _ in blocks if s.closure is not None), None)
        offset = 0
        for (space, x), p in zip(blocks, sizes, strict=True):
            k, sc, eff, w = space.settings(x)
            faults.append(k)
            for f, v in sc.items():
                scales.setdefault(f, torch.ones(total, dtype=torch.float64))[offset : offset + p] = v
            for name in names:
                vals = eff.get(name) or _off(name, p)
                dest = effects.setdefault(name, {})
                for key, v in vals.items():
                    dest.setdefault(key, torch.zeros(total, dtype=torch.float64))[offset : offset + p] = v
            if closure_net is not None:
                closures.append(w if w is not None else torch.zeros(p, closure_net.n_weights, dtype=torch.float64))
            offset += p
        k_all = torch.cat(faults)
        outputs = [BlockOutput([{} for _ in self.records]) for _ in blocks]
        for group in self.groups:
            reps = len(group)
            eff_objs: list[Effect] = [EFFECTS[n](**{k: v.repeat(reps) for k, v in effects[n].items()}) for n in names]
            if closure_net is not None:
                eff_objs.append(NeuralClosure(closure_net, torch.cat(closures).repeat(reps, 1)))
            sim = EMASimulator(self.params, self.fidelity, effects=eff_objs, device=self.device)
            cmd = torch.cat([self.records[i].command.to(self.device).expand(total, -1) for i in group])
            rec0 = self.records[group[0]]
            with torch.no_grad(), threads(self.threads):
                sig = sim.run(
                    k_all.repeat(reps, 1),
                    cmd,
                    rec0.duration,
                    scales={f: v.repeat(reps) for f, v in scales.items()},
                    channels=self.sim_channels,
                )
            self.calls += 1
            self.simulated_rows += total * reps
            for g, i in enumerate(group):
                start = g * total
                off = 0
                for b, p in enumerate(sizes):
                    outputs[b].channels[i] = {c: sig[c][start + off : start + off + p].cpu() for c in self.sim_channels}
                    off += p
        return outputs

    def residuals(self, out: BlockOutput, sigma: Sequence[dict[str, float]]) -> torch.Tensor:
        """(simulated - measured) / sigma, concatenated over records and channels, (P, m)."""
        parts = []
        for i, rec in enumerate(self.records):
            for c in self.channels:
                parts.append((out.channels[i][c] - rec.measured[c]) / sigma[i][c])
        return torch.cat(parts, dim=-1)

    def split(self, r: torch.Tensor) -> list[dict[str, torch.Tensor]]:
        """Inverse of the concatenation of :meth:`residuals`: (..., m) -> per record {channel: (..., n_r)}."""
        out, pos = [], 0
        for rec in self.records:
            d = {}
            for c in self.channels:
                d[c] = r[..., pos : pos + len(rec)]
                pos += len(rec)
            out.append(d)
        return out


def _off(name: str, p: int) -> dict[str, torch.Tensor]:
    """Values of effect ``name`` switched off: strengths 0, other parameters at their defaults; each (p,)."""
    cls = EFFECTS[name]
    vals = effect_defaults(name)
    return {k: torch.full((p,), 0.0 if k in cls.STRENGTH else v, dtype=torch.float64) for k, v in vals.items()}
