"""Corruption suite: every kind of :mod:`phm_torch.online.corruptions` at its severities, on nominal and faulty HF
records of the pipeline's actuator, through the exported pipeline on phm-predict's code path
(:func:`phm_torch.online.diagnosis.diagnose`); plus records simulated under changed conditions (another actuator,
a wrong command amplitude or frequency). Per kind: the mildest severity from which every case is flagged, and for
the unflagged cases whether the answer is still right (every damage component's truth within its interval,
widened by ``TOLERANCE``, and the verdict that of the health classifier on the true k); the false-rejection rate
on clean val-like records (random fault vectors, 0-3 % noise); the cost of the checks.

``scripts/corruption_suite.py`` is its command line (writes the JSON); ``tests/test_corruptions.py`` runs it on two
records. The HF records are simulated once and cached under ``CACHE``.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import math
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
from hydra.utils import instantiate

from phm_torch import provenance
from phm_torch.data.sampling import ImportanceSampler
from phm_torch.faults import FAULT_NAMES
from phm_torch.io.atomic import atomic_open
from phm_torch.online.corruptions import CORRUPTIONS, Record, corrupt
from phm_torch.online.diagnosis import calibrated_interval, contract_for, diagnose
from phm_torch.online.export import read_metadata
from phm_torch.online.input_contract import PIPELINE_CHECKS, InputContract
from phm_torch.params import CONF_DIR, ActuatorParams
from phm_torch.simulator import EMASimulator

PIPELINE = CONF_DIR.parent / "pretrained" / "online_surrogates_best.pt"
CACHE = Path("/tmp/phm_corruption_records")
DAMAGE = [i for i, name in enumerate(FAULT_NAMES) if name != "eccentricity_phase"]
CLEAN_NOISE = (0.0, 0.01, 0.02, 0.03)  # relative current noise of the clean records (issue 24: <= 1 % flagged)
TOLERANCE = 0.02  # an interval missed by less than this still counts as right (90 % intervals)
SUITE_NOISE = 0.01  # relative current noise of the suite's records (the calibration's)
# the suite's fault vectors as moves from nominal: nominal, dry friction x1.6, 40 % of phase A shorted
# (healthy), backlash x20 with gain drift
MOVES = ({}, {0: 0.3}, {2: 0.4}, {1: 0.2, 7: 0.2})
MOTOR = ("back_emf_constant", "phase_resistance", "phase_inductance", "motor_inertia")
SIMULATED = {  # kinds simulated under changed conditions: severities, unit, description
    "other_actuator": ((0.1, 0.3, 0.6), "motor values x (1 + s)", f"another motor: {', '.join(MOTOR)} scaled"),
    "command_amplitude": ((0.2, 0.5, 1.0), "amplitude x (1 + s)", "the test run at another amplitude"),
    "command_frequency": (
        (0.2, 0.5, 1.0),
        "end frequency (or playback rate) x (1 + s)",
        "the test run at another chirp rate (a command without an end frequency: played faster)",
    ),
}


@dataclass(frozen=True)
class _Replayed:
    """``base`` played with its positions x ``gain`` and its time axis x ``speed``: the wrong-amplitude and wrong-rate
    runs of a command that has no ``amplitude`` or ``f_end`` parameter to change (a profile, a multisine)."""

    base: Any
    gain: float = 1.0
    speed: float = 1.0

    @property
    def duration(self) -> float:
        return float(self.base.duration)

    def __call__(self, t: torch.Tensor) -> torch.Tensor:
        return self.gain * self.base(t * self.speed)


@dataclass(frozen=True)
class Case:
    """One record of the suite with its truth: k (8,) and the health classifier's verdict on it."""

    record: Record
    k: torch.Tensor
    healthy: bool


def _simulate(params: ActuatorParams, k: torch.Tensor, command: Any, cache: Path, tag: str) -> dict[str, torch.Tensor]:
    """HF records (time, command, position, current) of fault vectors k (B, 8); cached by their inputs."""
    key = hashlib.sha256(
        json.dumps(
            [provenance.actuator_values(params), k.tolist(), repr(command), tag], sort_keys=True, default=str
        ).encode()
    ).hexdigest()[:16]
    path = cache / f"{tag}_{key}.pt"
    if path.is_file():
        return torch.load(path, weights_only=True)
    duration = float(command.duration)
    sig = EMASimulator(params, "hf").run(k, command, duration, channels=["current", "position"])
    out = {
        "time": sig.time,
        "command": command(sig.time).expand(k.shape[0], -1).clone(),
        "position": sig["position"],
        "current": sig["current"],
        "k": k,
    }
    cache.mkdir(parents=True, exist_ok=True)
    with atomic_open(path, "wb") as fh:
        torch.save(out, fh)
    return out


def pipeline_conditions(path: Path) -> tuple[ActuatorParams, dict[str, Any], Any]:
    """The actuator, the command node and the command of an exported pipeline (from its metadata)."""
    prov = read_metadata(path).get("provenance") or {}
    if not prov.get("actuator") or not prov.get("command"):
        raise ValueError(f"{path}: the pipeline records no actuator and command; the suite needs both")
    node = dict(prov["command"]["params"])
    return ActuatorParams.from_mapping(prov["actuator"]["values"]), node, instantiate(node)


def truth_healthy(model: Any, k: torch.Tensor) -> list[bool]:
    """The health classifier's verdict on the true fault vectors k (B, 8)."""
    with torch.no_grad():
        return (model.classifier(k.to(model.times.dtype)) > model.classifier.threshold).tolist()


def _cases(sim: dict[str, torch.Tensor], model: Any, noise: float, rng: np.random.Generator) -> list[Case]:
    """The simulated records with ``noise`` (relative to each record's RMS) of white current noise."""
    cases = []
    for i, healthy in enumerate(truth_healthy(model, sim["k"])):
        cur = sim["current"][i]
        cur = cur + noise * float(cur.pow(2).mean().sqrt()) * torch.as_tensor(rng.standard_normal(cur.numel()))
        cases.append(Case(Record(sim["time"], sim["command"][i], sim["position"][i], cur), sim["k"][i], healthy))
    return cases


def suite_records(
    model: Any, path: Path, cache: Path = CACHE, moves: tuple[dict[int, float], ...] = MOVES, simulated: bool = True
) -> tuple[list[Case], dict[str, dict[float, list[Case]]]]:
    """The suite's records of the pipeline's actuator on its command, and those simulated under changed
    conditions per kind and severity (nominal and the first fault of ``moves``)."""
    params, node, command = pipeline_conditions(path)
    nominal = torch.tensor(params.nominal_faults, dtype=torch.float64)
    k = nominal.repeat(len(moves), 1)
    for row, move in enumerate(moves):
        for j, value in move.items():
            k[row, j] = nominal[j] + value
    rng = np.random.default_rng(0)
    base = _cases(_simulate(params, k, command, cache, "suite"), model, SUITE_NOISE, rng)
    changed: dict[str, dict[float, list[Case]]] = {}
    if not simulated:
        return base, changed
    pair = k[:2]
    for kind, (severities, _, _) in SIMULATED.items():
        changed[kind] = {}
        for s in severities:
            p, cmd = params, command
            if kind == "other_actuator":
                p = params.replace(**{name: getattr(params, name) * (1.0 + s) for name in MOTOR})
            elif kind == "command_amplitude":
                if "amplitude" in node:
                    cmd = instantiate({**node, "amplitude": node["amplitude"] * (1.0 + s)})
                else:
                    cmd = _Replayed(command, gain=1.0 + s)
            elif "f_end" in node:
                cmd = instantiate({**node, "f_end": node["f_end"] * (1.0 + s)})
            else:
                cmd = _Replayed(command, speed=1.0 + s)
            changed[kind][s] = _cases(_simulate(p, pair, cmd, cache, kind), model, SUITE_NOISE, rng)
    return base, changed


def clean_record_arguments(description: str, out: str) -> argparse.ArgumentParser:
    """The command line of a script that reads the clean val-like records of a pipeline's actuator
    (``--pipeline``, ``--vectors``, ``--out`` defaulting to ``out``, ``--cache``); :func:`clean_records` reads them."""
    parser = argparse.ArgumentParser(description=description)
    parser.add_argument("--pipeline", type=Path, default=PIPELINE)
    parser.add_argument("--vectors", type=int, default=500, help="fault vectors of the clean records")
    parser.add_argument("--out", type=Path, default=Path(out))
    parser.add_argument("--cache", type=Path, default=CACHE)
    return parser


def clean_records(model: Any, path: Path, n: int = 500, cache: Path = CACHE, seed: int = 1) -> list[Case]:
    """Val-like records: ``n`` fault vectors drawn as the paper's store draws them, each at 0, 1, 2 and 3 %
    noise, twice (8 n records)."""
    params, _, command = pipeline_conditions(path)
    nominal = tuple(params.nominal_faults)
    uniform = tuple(i for i, name in enumerate(FAULT_NAMES) if name == "eccentricity_phase")
    k = torch.as_tensor(ImportanceSampler(nominal, uniform, 1.0).sample(n, seed), dtype=torch.float64)
    sim = _simulate(params, k, command, cache, "clean")
    rng = np.random.default_rng(seed)
    return [c for level in CLEAN_NOISE for _ in range(2) for c in _cases(sim, model, level, rng)]


def judge(
    model: Any,
    case: Case,
    record: Record,
    contract: InputContract,
    current_only: bool = False,
    remove_lines: bool = True,
) -> dict[str, Any]:
    """The diagnosis of a (corrupted) record on phm-predict's path, and whether it is flagged or still right
    (``remove_lines``: as :func:`~.diagnosis.diagnose`)."""
    if current_only:
        record = Record(record.time, None, None, record.current)
    out = diagnose(model, record, contract, remove_lines=remove_lines)
    if out["out_of_distribution"]:
        # flagged: phm-predict reports no interval; the calibrated one at its noise says whether the answer the flag
        # withheld was right (a false rejection) or wrong
        lower, upper = calibrated_interval(model, out)
        out = {**out, "k_interval": {n: [a, b] for n, a, b in zip(FAULT_NAMES, lower.tolist(), upper.tolist())}}
    return judgement(out, case.k, case.healthy)


def judgement(out: dict[str, Any], k: torch.Tensor, healthy: bool) -> dict[str, Any]:
    """Whether a diagnosis (phm-predict's JSON record) is flagged, and if not whether it is right: the verdict
    that of the health classifier on the true k (8,), every damage component inside its interval (within
    ``TOLERANCE``); ``err_k``: mean |k_hat - k| over the damage components."""
    verdict_right = out["healthy"] == healthy
    inside, each = None, None
    truth = k.double()
    if out["k_interval"] is not None:
        bounds = torch.tensor([out["k_interval"][name] for name in FAULT_NAMES], dtype=torch.float64)
        each = ((truth >= bounds[:, 0] - TOLERANCE) & (truth <= bounds[:, 1] + TOLERANCE))[DAMAGE]
        inside = bool(each.all())
    k_hat = torch.tensor([out["k_hat"][name] for name in FAULT_NAMES], dtype=torch.float64)
    return {
        "flagged": out["out_of_distribution"],
        "reasons": out["ood_reasons"],
        "right": bool(verdict_right and inside),
        "verdict_right": verdict_right,
        "inside": inside,
        "inside_each": None if each is None else each.tolist(),
        "err_k": float((k_hat - truth).abs()[DAMAGE].mean()),
    }


def contract_of(model: Any, path: Path) -> InputContract:
    """The pipeline's input contract, as phm-predict builds it."""
    return contract_for(model, read_metadata(path), pipeline_conditions(path)[2])


def _summary(severities: tuple[float, ...], results: dict[float, list[dict[str, Any]]]) -> dict[str, Any]:
    """Per kind: the mildest severity from which every case (at it and above) is flagged, the severities with
    an unflagged wrong answer (the blind spots), and per severity the counts and reasons."""
    flagged_from = None
    for s in reversed(severities):
        if all(r["flagged"] for r in results[s]):
            flagged_from = s
        else:
            break
    wrong = [s for s in severities if any(not r["flagged"] and not r["right"] for r in results[s])]
    per = {
        str(s): {
            "cases": len(results[s]),
            "flagged": sum(r["flagged"] for r in results[s]),
            "unflagged_right": sum(not r["flagged"] and r["right"] for r in results[s]),
            "unflagged_wrong": sum(not r["flagged"] and not r["right"] for r in results[s]),
            "reasons": sorted({x for r in results[s] for x in r["reasons"]}),
        }
        for s in severities
    }
    return {"flagged_from": flagged_from, "wrong_unflagged_at": wrong, "severities": per}


def run_suite(
    model: Any,
    path: Path,
    cases: list[Case],
    changed: dict[str, dict[float, list[Case]]],
    kinds: list[str] | None = None,
    seed: int = 0,
) -> dict[str, dict[str, Any]]:
    """Every corruption kind (``kinds``: a subset) at its severities over ``cases``, and the simulated kinds of
    ``changed``; each case with its command and position columns (``full``) and as a current-only record."""
    contract = contract_of(model, path)
    rng = np.random.default_rng(seed)
    table: dict[str, dict[str, Any]] = {}
    for kind in kinds if kinds is not None else list(CORRUPTIONS):
        spec = CORRUPTIONS[kind]
        modes: dict[str, dict[float, list[dict[str, Any]]]] = {"full": {}, "current_only": {}}
        for s in spec.severities:
            records = [(case, corrupt(kind, case.record, s, rng)) for case in cases]
            for mode, results in modes.items():
                results[s] = [judge(model, c, r, contract, mode == "current_only") for c, r in records]
        table[kind] = {
            "unit": spec.unit,
            "description": spec.description,
            **{mode: _summary(spec.severities, res) for mode, res in modes.items()},
        }
    for kind, by_severity in changed.items():
        severities, unit, description = SIMULATED[kind]
        modes = {
            mode: {
                s: [judge(model, c, c.record, contract, mode == "current_only") for c in by_severity[s]]
                for s in severities
            }
            for mode in ("full", "current_only")
        }
        table[kind] = {
            "unit": unit,
            "description": description,
            "simulated": True,
            **{mode: _summary(severities, res) for mode, res in modes.items()},
        }
    return table


def blind_spots(table: dict[str, dict[str, Any]]) -> dict[str, list[str]]:
    """The kinds with an unflagged wrong answer at some severity, per mode."""
    return {
        mode: sorted(k for k, v in table.items() if v[mode]["wrong_unflagged_at"]) for mode in ("full", "current_only")
    }


def false_rejections(model: Any, path: Path, cases: list[Case]) -> dict[str, Any]:
    """Flagged share of clean records (with their command and position columns), and the reasons."""
    contract = contract_of(model, path)
    results = [judge(model, c, c.record, contract) for c in cases]
    reasons: dict[str, int] = {}
    for r in results:
        for x in r["reasons"]:
            reasons[x] = reasons.get(x, 0) + 1
    flagged = sum(r["flagged"] for r in results)
    per_level = len(results) // len(CLEAN_NOISE)  # clean_records orders the records by noise level
    by_noise = {
        str(level): sum(r["flagged"] for r in results[i * per_level : (i + 1) * per_level]) / per_level
        for i, level in enumerate(CLEAN_NOISE)
    }
    new = sum(any(x not in PIPELINE_CHECKS and x != "pipeline" for x in r["reasons"]) for r in results)
    kept = [r for r in results if not r["flagged"]]
    each = [r["inside_each"] for r in kept if r["inside_each"] is not None]
    return {
        "records": len(results),
        "flagged": flagged,
        "rate": flagged / len(results),
        "rate_by_noise": by_noise,
        "reasons": reasons,
        "flagged_by_new_checks": new,
        "rate_new_checks": new / len(results),
        # a flagged record whose withheld answer was right (k_hat within its calibrated interval, verdict right): the
        # false rejections proper; flagged and wrong: the flag did its job
        "flagged_right": sum(r["flagged"] and r["right"] for r in results),
        "false_rejection_rate": sum(r["flagged"] and r["right"] for r in results) / len(results),
        "flagged_wrong": sum(r["flagged"] and not r["right"] for r in results),
        "unflagged_wrong": sum(not r["flagged"] and not r["right"] for r in results),
        # why an unflagged clean record counts as wrong: its verdict, or a component outside its interval (the
        # intervals are per parameter at their calibrated coverage, so some joint misses are expected)
        "unflagged_verdict_wrong": sum(not r["verdict_right"] for r in kept),
        "unflagged_outside_interval": sum(r["inside"] is False for r in kept),
        "interval_coverage_unflagged": (
            {FAULT_NAMES[d]: sum(e[i] for e in each) / len(each) for i, d in enumerate(DAMAGE)} if each else None
        ),
    }


def check_cost(model: Any, path: Path, cases: list[Case], repeats: int = 3) -> dict[str, float]:
    """us per record of the input contract's checks (pipeline reasons included, the command check's lag search
    excluded: it runs only on a failed command) and of the pipeline's forward, one record at a time."""
    contract = contract_of(model, path)
    xs = [c.record.current.to(model.times.dtype).unsqueeze(0) for c in cases]
    best = {"contract_us": math.inf, "contract_flagged_us": math.inf, "forward_us": math.inf}
    with torch.no_grad():
        for _ in range(repeats):
            t0 = time.perf_counter()
            for x in xs:
                model(x)
            best["forward_us"] = min(best["forward_us"], (time.perf_counter() - t0) / len(xs) * 1e6)
            for key, ood in (("contract_us", False), ("contract_flagged_us", True)):
                t0 = time.perf_counter()
                for c, x in zip(cases, xs):
                    contract.check(model, c.record, x[0], float(model.noise_level(x)[0]), ood)
                best[key] = min(best[key], (time.perf_counter() - t0) / len(xs) * 1e6)
    return {k: round(v, 1) for k, v in best.items()}
