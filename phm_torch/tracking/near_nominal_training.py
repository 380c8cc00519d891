"""Train and calibrate a pipeline's near-nominal FDI (:class:`~.near_nominal.NearNominalFDI`) from a life split.

Training rows: the records of a life split (run-to-failure histories) but a held-out share of its actuators, and,
optionally, the near-nominal records of a store split (every damage at most ``max_damage``); every 2,000 steps each
row gets a fresh relative noise level, uniform up to 1.1 x the last of ``noise_levels`` (a life record at least its
own), and a fresh draw of white noise to reach it. The held-out actuators, brought to each of ``noise_levels``,
calibrate the 90 % half-widths per component and level (then widened by ``width_factor``: the held-out errors
persist from one inspection to the next, which the filter fuses as independent) and give the errors reported in
the file's provenance. ``scripts/fit_near_nominal.py`` and phm-run's ``companions`` stage call
:func:`train_near_nominal`.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import h5py
import numpy as np
import torch

from .. import provenance
from ..faults import FAULT_NAMES
from ..io import read_measurement
from ..online.diagnosis import not_identified
from ..online.loaded import load_pipeline
from .near_nominal import PHASE_INDEX, NearNominalFDI, TooFewNearNominalRecords, fit_near_nominal
from .response import probe_k_hat


@dataclass
class NearNominalTraining:
    """Settings of :func:`train_near_nominal`.

    Args:
        full_record: principal directions of the training records the network reads every sample of the record
            on (0: the pipeline's gappy coefficients of its selected samples instead).
        max_damage: store records are used where every damage is at most this.
        noise_levels: increasing relative noise levels the half-widths are calibrated at (read up to the last).
        holdout: every n-th actuator of the life split (sorted by name) calibrates and is not trained on.
        steps: Adam steps.
        gate: the pipeline's largest damage up to which the network is read.
        width_factor: >= 1, multiplies the calibrated half-widths (1.25 for the shipped file, chosen on the
            tracker's coverage of held-out histories; docs/prognostics.md).
        seed: noise draws, batches and initial weights.
        store_split: the store's split read (``rul``: a store made with ``n_rul`` and ``rul_radius`` is all near
            nominal).
    """

    full_record: int = 64
    max_damage: float = 0.2
    noise_levels: tuple[float, ...] = (0.01, 0.02, 0.03, 0.04)
    holdout: int = 5
    steps: int = 40000
    gate: float = 0.25
    width_factor: float = 1.25
    seed: int = 0
    store_split: str = "train"

    def __post_init__(self) -> None:
        self.noise_levels = tuple(float(v) for v in self.noise_levels)
        checks = (
            ("full_record", self.full_record, isinstance(self.full_record, int) and self.full_record >= 0),
            ("max_damage", self.max_damage, 0.0 < self.max_damage <= 1.0),
            ("holdout", self.holdout, isinstance(self.holdout, int) and self.holdout >= 2),
            ("steps", self.steps, isinstance(self.steps, int) and self.steps >= 1),
            ("gate", self.gate, 0.0 < self.gate <= 1.0),
            ("width_factor", self.width_factor, math.isfinite(self.width_factor) and self.width_factor >= 1.0),
            (
                "noise_levels",
                list(self.noise_levels),
                len(self.noise_levels) > 0
                and all(0.0 < v < 1.0 for v in self.noise_levels)
                and all(a < b for a, b in zip(self.noise_levels, self.noise_levels[1:])),
            ),
        )
        for name, value, ok in checks:
            if not ok:
                raise ValueError(f"near-nominal training: {name} = {value!r} is outside its range (see the docstring)")


def life_records(
    root: Path, model: Any, full: bool = False
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, list[str]]:
    """(samples (N, n_w), or with ``full`` the records (N, n_full) [A]; record RMS (N,) [A], the pipeline's noise
    level (N,), true k (N, 8), actuator of each row) of every inspection of the life split in ``root``."""
    idx = slice(None) if full else model.gappy.indices.numpy()
    truth_path = root / "truth.json"
    if not truth_path.is_file():
        raise ValueError(f"life: no truth.json in {str(root)!r} (a life split of phm-generate)")
    truth = json.loads(truth_path.read_text())["actuators"]
    samples, scale, noise, k, who = [], [], [], [], []
    for actuator, info in truth.items():
        for ins in info["inspections"]:
            current = read_measurement(root / ins["file"]).current  # float64 (n_full,) [A]
            samples.append(current[idx])
            scale.append(float(np.sqrt((current**2).mean())))
            with torch.no_grad():
                noise.append(float(model.noise_level(torch.as_tensor(current, dtype=model.times.dtype)[None])[0]))
            k.append(ins["k_true"])
            who.append(actuator)
    if not samples:
        raise ValueError(f"life: the split in {str(root)!r} has no inspections")
    return np.array(samples), np.array(scale), np.array(noise), np.array(k), who


def store_records(
    store: Path, idx: Any, nominal: np.ndarray, max_damage: float, split: str = "train"
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(samples, record RMS, k) of the store's ``split`` records whose every damage is at most ``max_damage``."""
    path = store / "dataset.h5"
    if not path.is_file():
        raise ValueError(f"store: no dataset.h5 in {str(store)!r}")
    with h5py.File(path, "r") as f:
        if split not in f:
            raise ValueError(f"store_split: {split!r} is not a split of {str(path)!r} (it has {sorted(f)})")
        k = f[split]["K"][:]
        damage = np.abs(k - nominal)
        damage[:, PHASE_INDEX] = 0.0
        keep = np.where(damage.max(1) <= max_damage)[0]
        samples, scale = [], []
        current = f[split]["current"]
        for start in range(0, k.shape[0], 4000):
            rows = keep[(keep >= start) & (keep < start + 4000)] - start
            block = current[start : start + 4000][rows].astype(np.float64)
            samples.append(block[:, idx])
            scale.append(np.sqrt((block**2).mean(1)))
    n_w = (samples[0].shape[1] if samples else 0) if isinstance(idx, slice) else len(idx)
    if not samples:
        return np.zeros((0, n_w)), np.zeros(0), np.zeros((0, len(FAULT_NAMES)))
    return np.concatenate(samples), np.concatenate(scale), k[keep]


def train_near_nominal(
    pipeline: str | Path,
    life: str | Path,
    settings: NearNominalTraining | None = None,
    store: str | Path | None = None,
) -> tuple[NearNominalFDI, dict[str, Any]]:
    """The near-nominal FDI of the exported pipeline at ``pipeline``, trained on the life split in ``life`` (and
    the near-nominal records of ``store``'s ``settings.store_split``), calibrated on its held-out actuators.

    Returns (network with its ``provenance`` set, ready to :meth:`~.near_nominal.NearNominalFDI.save`; that
    provenance). ValueError naming the input for a life split or store that cannot be read."""
    s = settings or NearNominalTraining()
    loaded = load_pipeline(pipeline)
    model = loaded.module
    full = s.full_record > 0
    idx = slice(None) if full else model.gappy.indices.numpy()
    nominal = model.nominal.double().numpy()
    life_s, life_scale, life_noise, life_k, who = life_records(Path(life), model, full)
    actuators = sorted(set(who))
    held = {a for i, a in enumerate(actuators) if i % s.holdout == 0}
    if len(held) == len(actuators):
        raise TooFewNearNominalRecords(
            f"life: {len(actuators)} actuator(s) leave none to train on with holdout = {s.holdout}"
        )
    cal = np.array([a in held for a in who])
    if store is not None:
        store_s, store_scale, store_k = store_records(Path(store), idx, nominal, s.max_damage, s.store_split)
        store_s = store_s.reshape(-1, life_s.shape[1])  # none near nominal: (0, n_w)
    else:
        store_s, store_scale, store_k = np.zeros((0, life_s.shape[1])), np.zeros(0), np.zeros((0, len(FAULT_NAMES)))
    levels = list(s.noise_levels)
    net = NearNominalFDI(
        s.full_record if full else int(model.gappy.modes_hat.shape[1]),
        nominal=nominal.tolist(),
        gate=s.gate,
        noise_levels=levels,
        n_full=int(model.n_full) if full else None,
    )
    # the gate reads what the pipeline identifies (its phm-evaluate R^2; every damage for a pipeline without it)
    net.gate_on(not_identified(loaded.metadata))
    explained = None
    held_selected = life_s[cal][:, model.gappy.indices.numpy()] if full else life_s[cal]  # what the pipeline reads
    if full:  # the basis from the training rows; every row projected once: noise is then added to the coefficients,
        # white of the same std on each (orthonormal basis), as adding it to the record and projecting would
        train_rows = np.concatenate([store_s, life_s[~cal]])
        explained = net.fit_basis(torch.as_tensor(train_rows)).sum().item()
        del train_rows
        with torch.no_grad():
            life_s = net.coefficients(model, torch.as_tensor(life_s))[0].numpy()
            store_s = net.coefficients(model, torch.as_tensor(store_s))[0].numpy()

    def alpha(samples: np.ndarray) -> torch.Tensor:
        if full:
            return torch.as_tensor(samples, dtype=torch.float64)
        with torch.no_grad():
            x = torch.as_tensor(samples, dtype=model.gappy.modes_hat.dtype)
            return torch.cat([model.gappy(b)[0] for b in x.split(4096)]).double()

    gen = np.random.default_rng(s.seed)
    top = levels[-1] * 1.1

    def noisier(samples: np.ndarray, scale: np.ndarray, now: np.ndarray, target: np.ndarray) -> np.ndarray:
        """The samples with white noise added to reach the relative level ``target`` from ``now`` (per row)."""
        extra = np.sqrt(np.clip(target**2 - now**2, 0.0, None)) * scale
        return samples + extra[:, None] * gen.standard_normal(samples.shape)

    train_s, train_scale, train_now = life_s[~cal], life_scale[~cal], life_noise[~cal]
    life_kt = torch.as_tensor(life_k[~cal])
    store_kt = torch.as_tensor(store_k)

    def fresh() -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Every row at a fresh noise level, uniform up to 1.1 x the last calibrated one (life rows: at least their
        own), and a fresh draw of it."""
        store_level = gen.uniform(0.002, top, store_s.shape[0])
        life_level = np.maximum(gen.uniform(0.002, top, train_s.shape[0]), train_now)
        a = torch.cat(
            [
                alpha(noisier(store_s, store_scale, np.zeros(store_s.shape[0]), store_level)),
                alpha(noisier(train_s, train_scale, train_now, life_level)),
            ]
        )
        return a, torch.as_tensor(np.concatenate([store_level, life_level])), torch.cat([store_kt, life_kt])

    fit_near_nominal(net, *fresh(), steps=s.steps, seed=s.seed, fresh=fresh)
    held_s, held_scale, held_now, held_k = life_s[cal], life_scale[cal], life_noise[cal], torch.as_tensor(life_k[cal])
    calibration = {}
    for i, level in enumerate(levels):  # the held-out histories at each level: the pipeline's estimates gate them
        target = np.maximum(np.full(held_s.shape[0], level), held_now)
        noisy = noisier(held_s, held_scale, held_now, target)
        level_n = torch.as_tensor(target)
        with torch.no_grad():  # the pipeline's gate reads the held-out records at that level
            x = torch.as_tensor(noisier(held_selected, held_scale, held_now, target), dtype=model.gappy.modes_hat.dtype)
            k_pipeline = model(x, level_n.to(model.times.dtype))[0].double()
        rms, n_gated = net.calibrate(i, alpha(noisy), held_k, k_pipeline, level_n)
        calibration[str(level)] = {"records": n_gated, "rms": dict(zip(FAULT_NAMES, rms.tolist()))}
    net.half_widths_.mul_(s.width_factor)
    recorded = loaded.metadata.get("provenance") or {}
    net.provenance = {
        "source": str(pipeline),
        "probe_k_hat": probe_k_hat(model),
        "actuator": provenance.describe(recorded.get("actuator")),
        "command": provenance.describe(recorded.get("command")),
        "life_split": str(life),
        "life_records": int((~cal).sum()),
        "calibration_records": int(cal.sum()),
        "calibration_actuators": len(held),
        "store": None if store is None else str(store),
        "store_split": s.store_split if store is not None else None,
        "store_records": int(store_k.shape[0]),
        "max_damage": s.max_damage,
        "width_factor": s.width_factor,
        "noise_levels": levels,
        "steps": s.steps,
        "input": f"full record, {s.full_record} principal directions" if full else "the pipeline's gappy coefficients",
        "gate_components": [n for n, on in zip(FAULT_NAMES, net.gate_components_.tolist()) if on],
        **({"basis_variance_fraction": explained} if full else {}),
        "heldout": calibration,
    }
    return net, net.provenance
