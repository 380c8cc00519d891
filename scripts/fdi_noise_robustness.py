"""The FDI and its health verdict on a store's records with measurement noise of several levels; writes JSON.

Adds Gaussian white noise of std ``level`` x each record's RMS current to the full records of the chosen
splits (seeded; the same noise for every bundle), estimates each record's level from the record itself
(:func:`phm_torch.surrogates.augment.noise_level`, what the online pipeline does), and runs each bundle's
gappy POD and FDI network on the selected samples; a noise-aware network (``model.network.noise_input``)
is told the estimated level, a plain one ignores it. Per bundle, split and level: err_k, err_k of the
records with no large fault, the largest per-parameter mean |k error| (k7 weighted by k6, as in err_k), the
largest per-parameter mean *signed* error (the bias noise puts into k_hat), the classifier's verdict on
k_hat against the actual health, and the median estimated level.

Usage: python scripts/fdi_noise_robustness.py --data-dir data/paper --bundle plain=results/train_best/surrogates.pt
           --bundle aware=results/train_noise/surrogates.pt [--splits val rul] [--levels 0 0.01 0.03 0.05 0.1]
           [--out results/fdi_noise_robustness.json]
"""

from __future__ import annotations

import argparse
import platform
import time

import torch

from phm_torch.data import DatasetStore
from phm_torch.data.store import recorded_actuator
from phm_torch.io.atomic import write_json
from phm_torch.surrogates import SurrogateBundle, add_noise, err_k, fdi_mae, noise_level, rms
from phm_torch.surrogates.bundle_specs import load_named_bundles
from phm_torch.surrogates.metrics import ECC_PHASE, err_k_by_fault_count


def level_metrics(
    bundle: SurrogateBundle, signals: torch.Tensor, k: torch.Tensor, healthy: torch.Tensor, nominal: torch.Tensor
) -> dict[str, float]:
    """The bundle's FDI on full records ``signals`` (B, n_e) [A] of fault vectors k (B, 8)."""
    level = noise_level(signals)
    k_hat = bundle.estimate(signals, level)
    with torch.no_grad():
        verdict = bundle.verdict_healthy(k_hat)
    bias = (k_hat - k).mean(0)
    bias[ECC_PHASE] = 0.0  # a phase: its sign means nothing
    return {
        "err_k": err_k(k_hat, k),
        "err_k_no_large_fault": err_k_by_fault_count(k_hat, k, nominal)["0"]["err_k"],
        "fdi_mae_max": max(fdi_mae(k_hat, k, weighted=True)),
        "bias_max": float(bias.abs().max()),
        "chain_accuracy": float((verdict == healthy).double().mean()),
        "noise_estimate_median": float(level.median()),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--data-dir", required=True)
    ap.add_argument("--bundle", action="append", required=True, help="[name=]path of a SurrogateBundle")
    ap.add_argument("--splits", nargs="+", default=["val", "rul"])
    ap.add_argument("--levels", nargs="+", type=float, default=[0.0, 0.01, 0.03, 0.05, 0.1])
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--out", default="results/fdi_noise_robustness.json")
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    bundles = load_named_bundles(args.bundle)
    t0 = time.perf_counter()
    results: dict[str, dict[str, dict[str, dict[str, float]]]] = {name: {} for name in bundles}
    with DatasetStore(args.data_dir) as store:
        for bundle in bundles.values():
            bundle.check_store(store.provenance, f"store {args.data_dir}")
        params = recorded_actuator(store.metadata)
        nominal = torch.tensor(
            params.nominal_faults if params is not None else [0.0] * 6 + [0.5, 0.5], dtype=torch.float64
        )
        for split in args.splits:
            view = store.split(split)
            k = torch.as_tensor(view.K[()], dtype=torch.float64)
            healthy = torch.as_tensor(view.healthy[()]).bool()
            clean = torch.as_tensor(view.current[()], dtype=torch.float64)
            for j, level in enumerate(args.levels):
                gen = torch.Generator().manual_seed(args.seed + 100 * j)
                signals = add_noise(clean, rms(clean), level, gen) if level > 0 else clean
                for name, bundle in bundles.items():
                    results[name].setdefault(split, {})[f"{level:g}"] = level_metrics(
                        bundle, signals, k, healthy, nominal
                    )
                    row = results[name][split][f"{level:g}"]
                    print(
                        f"{name:>10} {split:>5} noise {level:5.3f}: err_k {100 * row['err_k']:.2f} %, bias "
                        f"{100 * row['bias_max']:.2f} %, verdict {100 * row['chain_accuracy']:.1f} %",
                        flush=True,
                    )
    report = {
        "data_dir": args.data_dir,
        "bundles": dict(zip(bundles, args.bundle)),
        "levels": args.levels,
        "results": results,
        "wall_s": round(time.perf_counter() - t0, 1),
        "machine": {"platform": platform.platform(), "threads": args.threads},
    }
    write_json(args.out, report)


if __name__ == "__main__":
    main()
