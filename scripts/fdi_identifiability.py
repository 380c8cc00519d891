"""Where the signal stops being a smooth function of k: the FDI's floor, by fault count; writes JSON.

Re-simulates vectors of a store's split with the store's own actuator, fidelity, effects and test
command (recorded in its metadata), after random steps of 1e-3, 1e-2 and 1e-1 in k (the eccentricity phase
held), and reports per group of "large faults at once" (|k_i - k0_i| > 0.3, as ``err_k_by_fault_count``)
the median RMS change of the envelope current per step and the linearity ratio of
:func:`phm_torch.surrogates.identifiability.signal_sensitivity`. With ``--predictions`` (phm-train's
``predictions.pt`` on the same store) it adds the FDI's err_k of each group, measured on every signal
of the group.

Usage: python scripts/fdi_identifiability.py --data-dir data/paper [--predictions results/train/predictions.pt]
           [--per-group 34] [--out results/fdi_identifiability.json]
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
from phm_torch.io.atomic import write_json
from phm_torch.simulator import EMASimulator
from phm_torch.surrogates.identifiability import signal_sensitivity
from phm_torch.surrogates.metrics import err_k, fault_count

GROUPS = {"0": (0, 0), "1": (1, 1), "2": (2, 2), "3+": (3, 8)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--data-dir", required=True)
    ap.add_argument("--split", default="val")
    ap.add_argument("--predictions", default=None)
    ap.add_argument("--per-group", type=int, default=34)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--out", default="results/fdi_identifiability.json")
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    with DatasetStore(args.data_dir) as store:
        cfg = (store.metadata or {}).get("config") or {}
        if "actuator" not in cfg or "command" not in cfg or "dataset" not in cfg:
            raise SystemExit(
                f"fdi_identifiability: error: the store {args.data_dir!r} does not record the "
                f"actuator, command and dataset it was simulated with"
            )
        k = torch.as_tensor(np.asarray(store.split(args.split).K), dtype=torch.float64)
    params = recorded_actuator(store.metadata)
    command = instantiate(cfg["command"])
    duration = float(command.duration)
    spec = cfg["dataset"]
    sim = EMASimulator(
        params, spec.get("fidelity", "hf"), effects=spec.get("effects") or None, substeps=spec.get("substeps")
    )
    nominal = torch.tensor(params.nominal_faults, dtype=torch.float64)
    count = fault_count(k, nominal)

    def simulate(kk: torch.Tensor) -> torch.Tensor:
        return sim.run(kk, command, duration, channels=["current"])["current"]

    k_hat = None
    if args.predictions:
        pred = torch.load(args.predictions, weights_only=True)
        if not torch.allclose(pred["k"].double(), k, atol=1e-6):
            raise SystemExit(
                f"fdi_identifiability: error: --predictions {args.predictions!r} is not on the "
                f"{args.split} split of {args.data_dir!r}"
            )
        k_hat = pred["k_hat"].double()
    out: dict = {
        "data_dir": str(args.data_dir),
        "split": args.split,
        "seed": args.seed,
        "machine": platform.platform(),
        "threads": args.threads,
        "groups": {},
    }
    t0 = time.perf_counter()
    for name, (lo, hi) in GROUPS.items():
        members = torch.nonzero((count >= lo) & (count <= hi)).flatten()
        if len(members) == 0:
            continue
        chosen = members[: args.per_group]
        s = signal_sensitivity(simulate, k[chosen], seed=args.seed)
        row = {
            "n_signals": len(members),
            "n_probed": len(chosen),
            "steps": s["steps"].tolist(),
            "rms_change_median_A": s["rms_change"].median(0).values.tolist(),
            "rms_change_p90_A": s["rms_change"].quantile(0.9, dim=0).tolist(),
            "signal_rms_median_A": float(s["signal_rms"].median()),
            "linearity_median": float(s["linearity"].median()),
        }
        if k_hat is not None:
            row["err_k"] = err_k(k_hat[members], k[members])
        out["groups"][name] = row
        print(
            f"{name:>3}: {len(chosen)} of {len(members)} probed; RMS change per step "
            f"{', '.join(f'{v:.4f}' for v in row['rms_change_median_A'])} A; linearity "
            f"{row['linearity_median']:.1f}" + (f"; err_k {row['err_k']:.4f}" if k_hat is not None else ""),
            flush=True,
        )
    out["elapsed_s"] = time.perf_counter() - t0
    write_json(Path(args.out), out)
    print(json.dumps({"out": args.out, "elapsed_s": round(out["elapsed_s"], 1)}))


if __name__ == "__main__":
    main()
