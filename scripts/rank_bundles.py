"""Rank surrogate bundles by err_k on a large held-out split, with bootstrap intervals and paired differences.

A 500-signal val split pins err_k down only to about +/- 0.75 points (most of the squared error sits in
the few signals with several heavy faults), so two runs closer than that cannot be ranked on it. This
script runs each bundle's online FDI (gappy POD of the selected samples, the network told each record's
estimated noise level) on every record of a split, reads them in row blocks, and reports per bundle:
err_k, its percentile-bootstrap 95 % interval, err_k per number of heavy faults (0 / 1 / 2 / 3+), and the
paired bootstrap difference of each bundle against the first (same resampled signals for both, so the
spread shared by the two cancels); and the verdict on the estimates (``bundle.verdict_healthy``):
accuracy, missed faults, false alarms, and the records only one of the two bundles judges right, with the
exact McNemar p-value against the first. An independent evaluation store of 4,000 val signals takes about a
minute of HF simulation on one core:

    phm-generate experiment=paper_eval data_dir=data/paper_eval
    python scripts/rank_bundles.py --data-dir data/paper_eval --bundle 40k=results/a/surrogates.pt \
        --bundle 80k=results/b/surrogates.pt [--split val] [--noise 0.01] [--out results/rank_bundles.json]
"""

from __future__ import annotations

import argparse
import math
import platform
import time

import numpy as np
import torch
from omegaconf import DictConfig

from phm_torch.apps import common
from phm_torch.data import DatasetStore
from phm_torch.surrogates import SurrogateBundle, add_noise, noise_level, rms
from phm_torch.surrogates.bundle import load_named_bundles
from phm_torch.surrogates.metrics import bootstrap_err_k, confusion, err_k_per_signal, fault_count

BLOCK = 2000     # records read and corrupted at a time
N_BOOT = 2000
GROUPS = ("0", "1", "2", "3+")


def squared_errors(bundles: dict[str, SurrogateBundle], data_dir: str, split: str, noise: float,
                   seed: int) -> tuple[dict[str, torch.Tensor], torch.Tensor, dict[str, torch.Tensor], torch.Tensor]:
    """Per bundle, the squared err_k of every record (n,) float64; each record's heavy-fault count (n,);
    per bundle, the verdict on every record (n,) bool (True = healthy); and the records' health (n,) bool."""
    sq: dict[str, list[torch.Tensor]] = {name: [] for name in bundles}
    verdicts: dict[str, list[torch.Tensor]] = {name: [] for name in bundles}
    counts, healthy = [], []
    gen = torch.Generator().manual_seed(seed)
    with DatasetStore(data_dir) as store:
        for bundle in bundles.values():
            bundle.check_store(store.provenance, f"store {data_dir}")
        store_cfg = store.metadata.get("config") or {}
        nominal = torch.tensor(common.actuator(DictConfig(store_cfg)).nominal_faults if "actuator" in store_cfg
                               else [0.0] * 6 + [0.5, 0.5], dtype=torch.float64)
        view = store.split(split)       # a ValueError naming the store's splits if it has no such split
        for start in range(0, len(view), BLOCK):
            k = torch.as_tensor(np.asarray(view.K[start:start + BLOCK]), dtype=torch.float64)
            signals = torch.as_tensor(np.asarray(view.current[start:start + BLOCK]), dtype=torch.float64)
            if noise > 0:
                signals = add_noise(signals, rms(signals), noise, gen)
            level = noise_level(signals)
            counts.append(fault_count(k, nominal).clamp(max=3))
            healthy.append(torch.as_tensor(np.asarray(view.healthy[start:start + BLOCK])).bool())
            for name, bundle in bundles.items():
                k_hat = bundle.estimate(signals, level)
                sq[name].append(err_k_per_signal(k_hat, k).pow(2))
                verdicts[name].append(bundle.verdict_healthy(k_hat))
    return ({name: torch.cat(q) for name, q in sq.items()}, torch.cat(counts),
            {name: torch.cat(v) for name, v in verdicts.items()}, torch.cat(healthy))


def mcnemar_p(only_a: int, only_b: int) -> float:
    """Exact two-sided McNemar p-value of ``only_a`` against ``only_b`` discordant records."""
    n = only_a + only_b
    if n == 0:
        return 1.0
    tail = sum(math.comb(n, i) for i in range(min(only_a, only_b) + 1)) / 2.0 ** n
    return min(1.0, 2.0 * tail)


def verdict_table(verdicts: dict[str, torch.Tensor], healthy: torch.Tensor) -> dict[str, dict[str, object]]:
    """Per bundle: the verdict's accuracy, missed-fault and false-alarm rates, and against the first bundle
    the records only one of the two judges right (``only_<first>``, ``only_this``) with the McNemar p-value."""
    first = next(iter(verdicts))
    right_first = verdicts[first] == healthy
    out = {}
    for name, v in verdicts.items():
        conf = confusion(v, healthy)
        row: dict[str, object] = {k: conf[k] for k in ("accuracy", "missed_fault_rate", "false_alarm_rate")}
        if name != first:
            right = v == healthy
            a, b = int((right_first & ~right).sum()), int((right & ~right_first).sum())
            row.update({f"only_{first}": a, "only_this": b, "mcnemar_p": mcnemar_p(a, b)})
        out[name] = row
    return out


def ranking(sq: dict[str, torch.Tensor], counts: torch.Tensor, seed: int) -> dict[str, object]:
    """err_k [%], bootstrap interval, per-group err_k and paired differences against the first bundle."""
    n = len(counts)
    probs = torch.tensor([0.025, 0.5, 0.975], dtype=torch.float64)
    boot = bootstrap_err_k(torch.stack(list(sq.values())), N_BOOT, seed)       # paired: shared resamples
    boot_err = {name: boot[:, i] for i, name in enumerate(sq)}
    first = next(iter(sq))
    out: dict[str, object] = {"n": n, "group_share": {g: round(float((counts == c).double().mean()), 4)
                                                      for c, g in enumerate(GROUPS)}}
    for name, q in sq.items():
        lo, _, hi = torch.quantile(boot_err[name], probs).tolist()
        row = {"err_k_pct": 100 * float(q.mean().sqrt()), "ci95_pct": [100 * lo, 100 * hi],
               "err_k_by_heavy_faults_pct": {g: 100 * float(q[counts == c].mean().sqrt()) if (counts == c).any()
                                             else None for c, g in enumerate(GROUPS)}}
        if name != first:
            row[f"minus_{first}_pp"] = [100 * x for x in torch.quantile(boot_err[name] - boot_err[first], probs).tolist()]
        out[name] = row
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data-dir", required=True)
    ap.add_argument("--bundle", action="append", required=True, help="[name=]path of a SurrogateBundle (first = reference)")
    ap.add_argument("--split", default="val")
    ap.add_argument("--noise", type=float, default=0.0, help="relative current noise added to the records")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--out", default="results/rank_bundles.json")
    args = ap.parse_args()
    if not args.noise >= 0:
        raise ValueError(f"--noise must be >= 0, got {args.noise!r}")
    torch.set_num_threads(args.threads)
    bundles = load_named_bundles(args.bundle)
    t0 = time.perf_counter()
    sq, counts, verdicts, healthy = squared_errors(bundles, args.data_dir, args.split, args.noise, args.seed)
    report = {"data_dir": args.data_dir, "split": args.split, "noise": args.noise,
              "bundles": dict(zip(bundles, args.bundle)),
              "ranking": ranking(sq, counts, args.seed), "verdict": verdict_table(verdicts, healthy),
              "wall_s": round(time.perf_counter() - t0, 1),
              "machine": {"platform": platform.platform(), "threads": args.threads}}
    for name in bundles:
        row = report["ranking"][name]
        diff = next((f", {k} {v[1]:+.2f} [{v[0]:+.2f}, {v[2]:+.2f}] pp" for k, v in row.items()
                     if k.startswith("minus_")), "")
        v = report["verdict"][name]
        vs = f", McNemar p {v['mcnemar_p']:.3g}" if "mcnemar_p" in v else ""
        print(f"{name:>12}: err_k {row['err_k_pct']:.2f} % [{row['ci95_pct'][0]:.2f}, {row['ci95_pct'][1]:.2f}]{diff}; "
              f"verdict {100 * v['accuracy']:.2f} %, missed faults {100 * v['missed_fault_rate']:.2f} %{vs}")
    common.write_json(args.out, report)


if __name__ == "__main__":
    main()
