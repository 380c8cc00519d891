"""Do the out-of-distribution flags single out the wrong answers under a small modelling difference? Writes JSON.

Issue 24, part 5. Records of the pipeline's actuator on its test command are simulated (HF) with each effect
of the library added at **half its default strength** (every ``Effect.STRENGTH`` parameter halved: a bench
whose physics differs a little from the training model), 1 % current noise, and diagnosed on phm-predict's
path (:func:`phm_torch.online.diagnosis.diagnose`, input contract included), as measured ("raw") and with the
bench's own healthy record as ``baseline`` ("baseline", what ``phm-predict baseline=...`` does). Per effect and
mode it reports the flagged rate and, separately for the flagged and the unflagged records, the median err_k
(mean |k_hat - k| over the damage components), the verdict error rate and the wrong rate (verdict wrong or a
damage component outside its interval; the corruption suite's "right"). A flag that means something has
err_k and wrong rates on its flagged records well above those of its unflagged ones; a flag that rejects a
whole bench for a harmless difference has a high flagged rate with unflagged-like errors. The first row,
``none``, is the training model itself. In the baseline mode the bench's healthy record is also read as measured
(:mod:`phm_torch.online.bench_check`): a bench too far from the training model flags every record (``bench``).

    python scripts/trust_model_mismatch.py [--pipeline pretrained/online_surrogates_best.pt] [--n 60]
        [--effects cogging_torque ...] [--out scripts/trust_model_mismatch.json]
"""

from __future__ import annotations

import argparse
import hashlib
import json
import platform
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
import torch

from phm_torch import provenance
from phm_torch.data.sampling import ImportanceSampler
from phm_torch.effects import EFFECTS
from phm_torch.faults import FAULT_NAMES
from phm_torch.io.atomic import atomic_open
from phm_torch.online.bench_check import check_bench
from phm_torch.online.corruption_suite import CACHE, PIPELINE, contract_of, judgement, pipeline_conditions
from phm_torch.online.corruption_suite import truth_healthy as _truth
from phm_torch.online.corruptions import Record
from phm_torch.online.diagnosis import diagnose
from phm_torch.online.export import read_metadata
from phm_torch.simulator import EMASimulator

NOISE = 0.01  # relative current noise of the records (the calibration's)
STRENGTH = 0.5  # each effect at this fraction of its default strength (--strength)


def scaled_strength(name: str, strength: float = STRENGTH) -> dict[str, float]:
    """The effect's parameters with every strength parameter at ``strength`` x its default."""
    cls = EFFECTS[name]
    return {p: spec.default * (strength if p in cls.STRENGTH else 1.0) for p, spec in cls.PARAMS.items()}


def simulate(
    params: Any, k: torch.Tensor, command: Any, effects: dict[str, dict[str, float]], cache: Path
) -> dict[str, torch.Tensor]:
    """HF records of k (B, 8) and of the nominal vector (the last row) with ``effects``; cached by their inputs."""
    key = hashlib.sha256(
        json.dumps(
            [provenance.actuator_values(params), k.tolist(), repr(command), effects], sort_keys=True, default=str
        ).encode()
    ).hexdigest()[:16]
    path = cache / f"mismatch_{key}.pt"
    if path.is_file():
        return torch.load(path, weights_only=True)
    rows = torch.cat([k, torch.tensor([params.nominal_faults], dtype=k.dtype)])
    sig = EMASimulator(params, "hf", effects=effects).run(
        rows, command, float(command.duration), channels=["current", "position"]
    )
    out = {
        "time": sig.time,
        "command": command(sig.time).expand(rows.shape[0], -1).clone(),
        "position": sig["position"],
        "current": sig["current"],
    }
    cache.mkdir(parents=True, exist_ok=True)
    with atomic_open(path, "wb") as fh:
        torch.save(out, fh)
    return out


def _noisy(current: torch.Tensor, rng: np.random.Generator) -> torch.Tensor:
    return current + NOISE * current.pow(2).mean().sqrt() * torch.as_tensor(rng.standard_normal(current.numel()))


def _summary(rows: list[dict[str, Any]]) -> dict[str, Any]:
    """Counts, err_k median, verdict error and wrong rates of records (None for an empty group)."""
    if not rows:
        return {"n": 0, "err_k_median": None, "verdict_error_rate": None, "wrong_rate": None}
    return {
        "n": len(rows),
        "err_k_median": float(np.median([r["err_k"] for r in rows])),
        "verdict_error_rate": float(np.mean([not r["verdict_right"] for r in rows])),
        "wrong_rate": float(np.mean([not r["right"] for r in rows])),
    }


def condition(model: Any, pipeline: Path, k: torch.Tensor, sim: dict[str, torch.Tensor], seed: int) -> dict[str, Any]:
    """Diagnose the records of one model (raw and with its own noisy healthy record as baseline); summarise."""
    contract = contract_of(model, pipeline)
    healthy = _truth(model, k)
    rng = np.random.default_rng(seed)
    baseline = _noisy(sim["current"][-1], rng)
    records = [
        Record(sim["time"], sim["command"][i], sim["position"][i], _noisy(sim["current"][i], rng))
        for i in range(k.shape[0])
    ]
    out: dict[str, Any] = {}
    bench = check_bench(model, baseline)
    for mode, bench_nominal in (("raw", None), ("baseline", baseline)):
        rows = [
            judgement(
                diagnose(model, r, contract, bench_nominal, bench if bench_nominal is not None else None),
                k[i],
                healthy[i],
            )
            for i, r in enumerate(records)
        ]
        flagged = [r for r in rows if r["flagged"]]
        out[mode] = {
            "flagged_rate": len(flagged) / len(rows),
            "all": _summary(rows),
            "flagged": _summary(flagged),
            "unflagged": _summary([r for r in rows if not r["flagged"]]),
            "reasons": sorted({x for r in rows for x in r["reasons"]}),
        }
    out["bench_check"] = None if bench is None else bench.as_dict()
    return out


def main(argv: list[str] | None = None) -> dict[str, Any]:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--pipeline", type=Path, default=PIPELINE)
    ap.add_argument("--n", type=int, default=60, help="fault vectors (the paper's importance sampling)")
    ap.add_argument("--effects", nargs="*", default=None, help="effect names (default: the whole library)")
    ap.add_argument("--cache", type=Path, default=CACHE)
    ap.add_argument("--seed", type=int, default=3)
    ap.add_argument("--strength", type=float, default=STRENGTH, help="fraction of each effect's default strength")
    ap.add_argument("--out", type=Path, default=Path("scripts/trust_model_mismatch.json"))
    args = ap.parse_args(argv)
    unknown = [e for e in args.effects or [] if e not in EFFECTS]
    if unknown:
        raise SystemExit(f"trust_model_mismatch: error: --effects {unknown} unknown; known: {sorted(EFFECTS)}")
    if not args.strength > 0:
        raise SystemExit(f"trust_model_mismatch: error: --strength must be > 0, got {args.strength}")
    if args.n < 1:
        raise SystemExit(f"trust_model_mismatch: error: --n must be >= 1, got {args.n}")
    torch.set_num_threads(1)
    model = torch.jit.load(str(args.pipeline))
    params, _, command = pipeline_conditions(args.pipeline)
    nominal = tuple(params.nominal_faults)
    uniform = tuple(i for i, name in enumerate(FAULT_NAMES) if name == "eccentricity_phase")
    k = torch.as_tensor(ImportanceSampler(nominal, uniform, 1.0).sample(args.n, args.seed), dtype=torch.float64)
    t0 = time.perf_counter()
    conditions: dict[str, Any] = {}
    for name in ["none", *(args.effects if args.effects is not None else sorted(EFFECTS))]:
        effects = {} if name == "none" else {name: scaled_strength(name, args.strength)}
        sim = simulate(params, k, command, effects, args.cache)
        conditions[name] = {"effect": effects.get(name), **condition(model, args.pipeline, k, sim, args.seed)}
        raw, base = conditions[name]["raw"], conditions[name]["baseline"]
        print(
            f"{name:>28}: flagged {raw['flagged_rate']:.2f} (baseline {base['flagged_rate']:.2f}); err_k "
            f"flagged {raw['flagged']['err_k_median']} unflagged {raw['unflagged']['err_k_median']}; wrong "
            f"flagged {raw['flagged']['wrong_rate']} unflagged {raw['unflagged']['wrong_rate']}",
            flush=True,
        )
    meta = read_metadata(args.pipeline).get("provenance") or {}
    report = {
        "pipeline": str(args.pipeline),
        "actuator": meta.get("actuator"),
        "command": meta.get("command"),
        "n_vectors": args.n,
        "noise": NOISE,
        "strength": args.strength,
        "machine": platform.platform(),
        "conditions": conditions,
        "wall_s": round(time.perf_counter() - t0, 1),
    }
    args.out.parent.mkdir(parents=True, exist_ok=True)
    with atomic_open(args.out, "w") as fh:
        json.dump(report, fh, indent=1)
    return report


if __name__ == "__main__":
    main(sys.argv[1:])
