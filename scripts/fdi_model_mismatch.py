"""The FDI and health verdict on records from a model the surrogates were not trained on; writes JSON.

Re-simulates the fault vectors of a store's split with the store's own actuator, fidelity, effects and
test command (recorded in its metadata), once as recorded (the reference) and once with each other effect
of the library added at its default values: a stand-in for another implementation of the datasheet or a bench
with physics the simulator lacks. ``--substeps N`` adds the store's own model integrated with N substeps per
control period (a finer or coarser discretisation: the kind of difference another implementation has).
For every bundle and condition it reports
:func:`phm_torch.surrogates.model_mismatch.mismatch_metrics`: the size of the modelling difference
(median NRMSE of the current), err_k, the largest per-parameter error, the health verdict from k_hat,
and how many records the out-of-distribution checks flag: as measured ("raw") and moved onto the
training model with that model's own healthy record ("rebased", what ``phm-predict baseline=...`` does:
x - (nominal record with the effect - nominal record without)).

Usage: python scripts/fdi_model_mismatch.py --data-dir data/paper --bundle results/train/surrogates.pt
           [--bundle best=results/train_best/surrogates.pt] [--effects cogging_torque viscous_friction]
           [--substeps 40] [--limit 500] [--out results/fdi_model_mismatch.json]
"""

from __future__ import annotations

import argparse
import json
import platform
import time
from pathlib import Path

import numpy as np
import torch
from hydra.utils import instantiate

from phm_torch.data import DatasetStore
from phm_torch.data.store import recorded_actuator
from phm_torch.effects import EFFECTS
from phm_torch.io.atomic import write_json
from phm_torch.simulator import EMASimulator
from phm_torch.surrogates.bundle_specs import load_named_bundles
from phm_torch.surrogates.model_mismatch import mismatch_metrics


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--data-dir", required=True)
    ap.add_argument("--bundle", action="append", required=True, help="[name=]path of a SurrogateBundle")
    ap.add_argument("--split", default="val")
    ap.add_argument("--effects", nargs="*", default=None, help="effect names (default: the whole library)")
    ap.add_argument(
        "--substeps",
        type=int,
        action="append",
        default=[],
        help="also the store's model with this many substeps per control period (repeatable)",
    )
    ap.add_argument("--limit", type=int, default=None, help="the first N vectors of the split")
    ap.add_argument("--compile", action=argparse.BooleanOptionalAction, default=True)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--out", default="results/fdi_model_mismatch.json")
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    requested = args.effects
    unknown = [e for e in requested or [] if e not in EFFECTS]
    if unknown:
        raise SystemExit(f"fdi_model_mismatch: error: --effects {unknown} unknown; known: {sorted(EFFECTS)}")
    bundles = load_named_bundles(args.bundle)
    with DatasetStore(args.data_dir) as store:
        for bundle in bundles.values():
            bundle.check_store(store.provenance, f"store {args.data_dir}")
        cfg = (store.metadata or {}).get("config") or {}
        if "actuator" not in cfg or "command" not in cfg or "dataset" not in cfg:
            raise SystemExit(
                f"fdi_model_mismatch: error: the store {args.data_dir!r} does not record the "
                f"actuator, command and dataset it was simulated with"
            )
        split = store.split(args.split)
        k = torch.as_tensor(np.asarray(split.K), dtype=torch.float64)[: args.limit]
        healthy = torch.as_tensor(np.asarray(split.healthy)).bool()[: args.limit]
    params = recorded_actuator(store.metadata)
    command = instantiate(cfg["command"])
    spec = cfg["dataset"]
    own = spec.get("effects") or {}
    effects = [e for e in (sorted(EFFECTS) if requested is None else requested) if e not in own]

    bad = [n for n in args.substeps if n < 1]
    if bad:
        raise SystemExit(f"fdi_model_mismatch: error: --substeps must be >= 1, got {bad}")

    def simulate(effect: dict, substeps: int | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        if args.compile:  # each effect set is another graph, used once: free the previous ones
            torch.compiler.reset()
        sim = EMASimulator(
            params,
            spec.get("fidelity", "hf"),
            effects=effect,
            substeps=substeps or spec.get("substeps"),
            compile=args.compile,
        )
        rows = torch.cat([k, torch.tensor([params.nominal_faults], dtype=k.dtype)])
        current = sim.run(rows, command, float(command.duration), channels=["current"])["current"]
        return current[:-1], current[-1]

    out: dict = {
        "data_dir": str(args.data_dir),
        "split": args.split,
        "n_vectors": len(k),
        "store_effects": own,
        "bundles": dict(zip(bundles, args.bundle)),
        "machine": platform.platform(),
        "threads": args.threads,
        "conditions": {},
    }
    t0 = time.perf_counter()
    reference, reference_nominal = simulate(own)
    conditions = {"none": None, **{e: {**own, e: {}} for e in effects}, **{f"substeps_{n}": n for n in args.substeps}}
    for name, condition in conditions.items():
        if condition is None:
            signals, nominal = reference, reference_nominal
        elif isinstance(condition, int):
            signals, nominal = simulate(own, condition)
        else:
            signals, nominal = simulate(condition)
        rebased = signals - (nominal - reference_nominal)
        row = {
            b: {
                "raw": mismatch_metrics(bundle, k, healthy, reference, signals),
                "rebased": mismatch_metrics(bundle, k, healthy, reference, rebased),
            }
            for b, bundle in bundles.items()
        }
        out["conditions"][name] = row
        print(
            f"{name:>27}: NRMSE {next(iter(row.values()))['raw']['nrmse_median']:.4f}; "
            + "; ".join(
                f"{b} err_k {m['raw']['err_k']:.4f} (rebased {m['rebased']['err_k']:.4f}), chain "
                f"{m['raw']['chain_accuracy']:.3f} ({m['rebased']['chain_accuracy']:.3f}; missed "
                f"{m['raw']['chain_missed_fault_rate']:.3f}, false alarms {m['raw']['chain_false_alarm_rate']:.3f}), "
                f"OOD {m['raw']['ood_rate']:.3f}"
                for b, m in row.items()
            ),
            flush=True,
        )
    out["elapsed_s"] = time.perf_counter() - t0
    write_json(Path(args.out), out)
    print(json.dumps({"out": args.out, "elapsed_s": round(out["elapsed_s"], 1)}))


if __name__ == "__main__":
    main()
