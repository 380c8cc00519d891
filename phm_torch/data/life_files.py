"""The files of the ``life`` split: per-actuator records and truth, resume, truth.json and index.csv.

Layout of ``<data_dir>/life/``: ``A000/0000.csv`` ... (one measurement CSV per inspection),
``A000/part.json`` (the actuator's truth, written last: its presence marks the actuator complete), and,
rewritten at the end from the parts, ``truth.json`` and ``index.csv`` (``actuator,hours,file``, files
relative to it). Every file is written atomically; a part of other settings (another key) is refused
unless ``overwrite``.
"""

from __future__ import annotations

import csv
import hashlib
import json
import math
import shutil
import sys
import time
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch
from tqdm import tqdm

from ..io import write_measurement
from ..io.atomic import atomic_open
from .life import LifeGenerator, actuator_ids

LIFE_DIR, TRUTH_FILE, INDEX_FILE, PART_FILE = "life", "truth.json", "index.csv", "part.json"


def _part_ok(path: Path, key: str) -> bool | None:
    """True: a complete actuator of this config; False: one of another config; None: not complete."""
    try:
        part = json.loads(path.read_text())
    except (OSError, ValueError):
        return None
    if part.get("key") != key:
        return False
    return all((path.parent / Path(i["file"]).name).is_file() for i in part.get("inspections", []))


def _json_k(k: torch.Tensor) -> list[float]:
    return [round(float(v), 12) for v in k]


def generate_life(
    out_dir: Path,
    generator: LifeGenerator,
    key_data: Mapping[str, Any],
    header: Mapping[str, Any],
    overwrite: bool = False,
    progress: bool = True,
) -> dict[str, Any]:
    """Write (or resume) the life split into ``out_dir``; returns its metrics.

    ``key_data``: everything the histories depend on (the life settings except ``n_actuators``, seed, actuator,
    command, damage, signal settings, assessment); an actuator part of another key is refused unless
    ``overwrite`` (then regenerated). ``header``: the top of truth.json (provenance, damage config...).
    """
    life = generator.life
    key = hashlib.sha256(json.dumps(key_data, sort_keys=True, default=str).encode()).hexdigest()
    ids = actuator_ids(life.n_actuators)
    out_dir.mkdir(parents=True, exist_ok=True)
    pending = []
    for i, name in enumerate(ids):
        adir = out_dir / name
        for stale in adir.glob(".*.tmp"):  # a temp file of a killed run: never data
            stale.unlink(missing_ok=True)
        state = _part_ok(adir / PART_FILE, key)
        if state is False:
            if not overwrite:
                raise ValueError(
                    f"{adir} holds an actuator made with different settings; choose another data_dir "
                    "or pass overwrite=true to regenerate it"
                )
            shutil.rmtree(adir)
        if not state:
            pending.append(i)
    t0 = time.perf_counter()
    histories = generator.histories(pending)
    n_rec = sum(int(h["hours"].numel()) for h in histories)
    bar = tqdm(total=n_rec, unit="record", desc="life", disable=not progress, file=sys.stderr, dynamic_ncols=True)
    # records in actuator order, simulated ``batch`` at a time; an actuator is written once all its are done
    flat = [(p, j) for p, h in enumerate(histories) for j in range(int(h["hours"].numel()))]
    buffered: dict[int, list[dict[str, torch.Tensor]]] = {}
    time_s = None
    # equal calls of at most ``batch`` records: one shape (a compiled simulator compiles once), little padding
    size = math.ceil(len(flat) / max(math.ceil(len(flat) / life.batch), 1)) if flat else life.batch
    try:
        for start in range(0, len(flat), size):
            part = flat[start : start + size]
            k = torch.stack([histories[p]["k"][j] for p, j in part])
            pad = size - k.shape[0]
            k = torch.cat([k, generator.nominal.expand(pad, -1)]) if pad else k
            t1 = time.perf_counter()
            time_s, sig = generator.simulate(k)
            generator.timing["simulate_s"] += time.perf_counter() - t1
            for row, (p, _) in enumerate(part):
                buffered.setdefault(p, []).append({c: sig[c][row] for c in ("command", "position", "current")})
            for p in sorted(buffered):
                if len(buffered[p]) == histories[p]["hours"].numel():
                    rows = buffered.pop(p)
                    sigs = {c: torch.stack([r[c] for r in rows]) for c in ("command", "position", "current")}
                    _write_actuator(out_dir, ids[pending[p]], pending[p], histories[p], generator, time_s, sigs, key)
            bar.update(len(part))
    finally:
        bar.close()
    wall = time.perf_counter() - t0
    truth = collect(out_dir, ids, header)
    counts = [len(a["inspections"]) for a in truth["actuators"].values()]
    censored = sum(a["eol_hours"] is None for a in truth["actuators"].values())
    return {
        "dir": str(out_dir),
        "actuators": len(ids),
        "computed": len(pending),
        "reused": len(ids) - len(pending),
        "records_computed": n_rec,
        "inspections": {
            "min": min(counts, default=0),
            "median": float(np.median(counts)) if counts else 0.0,
            "max": max(counts, default=0),
            "total": sum(counts),
        },
        "censored": censored,
        "wall_s": round(wall, 2),
        "s_per_actuator": round(wall / len(pending), 2) if pending else None,
        "phi_a_vectors": generator.phi_a_vectors,
        "timing_s": {k: round(v, 2) for k, v in generator.timing.items()},
    }


def _write_actuator(
    out_dir: Path,
    name: str,
    index: int,
    history: Mapping[str, Any],
    generator: LifeGenerator,
    time_s: torch.Tensor,
    signals: Mapping[str, torch.Tensor],
    key: str,
) -> None:
    """The actuator's CSVs, then its part.json (the completion mark), each atomically."""
    t0 = time.perf_counter()
    data = generator.records(index, time_s, signals)
    eol = history["eol_hours"]
    inspections = []
    for j, hours in enumerate(history["hours"].tolist()):
        rel = f"{name}/{j:04d}.csv"
        write_measurement(out_dir / rel, data, index=j, columns=())
        inspections.append(
            {
                "hours": hours,
                "file": rel,
                "k_true": _json_k(history["k"][j]),
                "healthy": bool(history["healthy"][j]),
                "rul_true": None if eol is None else round(eol - hours, 6),
            }
        )
    part = {
        "key": key,
        "rate_scale": history["rate_scale"],
        "eol_hours": None if eol is None else round(eol, 6),
        "censored": eol is None,
        "k0": _json_k(history["k0"]),
        "inspections": inspections,
    }
    with atomic_open(out_dir / name / PART_FILE, "w") as fh:
        json.dump(part, fh, indent=1)
    generator.timing["write_s"] += time.perf_counter() - t0


def collect(out_dir: Path, ids: Sequence[str], header: Mapping[str, Any]) -> dict[str, Any]:
    """Rewrite truth.json and index.csv (atomically) from the parts of ``ids``; returns the truth."""
    actuators = {}
    for name in ids:
        part = json.loads((out_dir / name / PART_FILE).read_text())
        part.pop("key", None)
        actuators[name] = part
    truth = {**header, "actuators": actuators}
    with atomic_open(out_dir / TRUTH_FILE, "w") as fh:
        json.dump(truth, fh, indent=1)
    with atomic_open(out_dir / INDEX_FILE, "w", newline="") as fh:
        writer = csv.writer(fh, lineterminator="\n")
        writer.writerow(["actuator", "hours", "file"])
        for name, part in actuators.items():
            writer.writerows([name, repr(float(i["hours"])), i["file"]] for i in part["inspections"])
    return truth
