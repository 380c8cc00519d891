"""Give a trained surrogate bundle a verdict classifier fitted on its own FDI estimates, without retraining.

``phm-train`` fits one (``verdict_classifier=true``, the default) right after the FDI network; this script
does the same for a bundle that lacks one (or replaces it), from the store the bundle was trained on:
the selected samples of every record of ``--split``, white noise of ``--noise`` times each record's RMS
current (the rated measurement noise, phm-train's ``eval.noise``), the bundle's FDI told that level, and
a classifier of the bundle's own kind and settings fitted on (k_hat, the records' health)
(:mod:`phm_torch.surrogates.verdict_classifier`). It reads the split in row blocks, so an 80,000-record
store needs little memory, and reports the verdict on ``--check-split`` before and after.

    python scripts/fit_verdict_classifier.py --bundle results/train/surrogates.pt --data-dir data/paper \
        --out results/train/surrogates_verdict.pt [--split train] [--noise 0.01] [--seed 11]
"""

from __future__ import annotations

import argparse
import json
import time

import numpy as np
import torch

from phm_torch.data import DatasetStore
from phm_torch.surrogates import SurrogateBundle, build_classifier, confusion, rms
from phm_torch.surrogates.verdict_classifier import fit_verdict_classifier

BLOCK = 4000     # records read at a time


def read_samples(bundle: SurrogateBundle, data_dir: str, split: str
                 ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Selected samples (N, n_w) [A], RMS currents (N,) [A] and health (N,) bool of a split's records."""
    samples, scale, healthy = [], [], []
    with DatasetStore(data_dir) as store:
        bundle.check_store(store.provenance, f"store {data_dir}")
        view = store.split(split)       # a ValueError naming the store's splits if it has no such split
        for start in range(0, len(view), BLOCK):
            x = torch.as_tensor(np.asarray(view.current[start:start + BLOCK]), dtype=bundle.pod.mean_.dtype)
            samples.append(bundle.compress(x))
            scale.append(rms(x))
            healthy.append(torch.as_tensor(np.asarray(view.healthy[start:start + BLOCK])).bool())
    if not samples:
        raise ValueError(f"split {split!r} of {data_dir!r} is empty")
    return torch.cat(samples), torch.cat(scale), torch.cat(healthy)


@torch.no_grad()
def verdicts(bundle: SurrogateBundle, data_dir: str, split: str) -> dict[str, dict[str, float]]:
    """Confusion of the health classifier and of the verdict on the FDI estimates of a split's records
    (the FDI told each record's estimated noise level, as the online pipeline does)."""
    k_hat, healthy = [], []
    with DatasetStore(data_dir) as store:
        view = store.split(split)
        for start in range(0, len(view), BLOCK):
            x = torch.as_tensor(np.asarray(view.current[start:start + BLOCK]), dtype=bundle.pod.mean_.dtype)
            k_hat.append(bundle.estimate(x))
            healthy.append(torch.as_tensor(np.asarray(view.healthy[start:start + BLOCK])).bool())
    k_hat, healthy = torch.cat(k_hat), torch.cat(healthy)
    keys = ("accuracy", "missed_fault_rate", "false_alarm_rate")
    return {name: {k: v for k, v in confusion(pred, healthy).items() if k in keys}
            for name, pred in (("health_classifier", bundle.is_healthy(k_hat)),
                               ("verdict", bundle.verdict_healthy(k_hat)))}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--bundle", required=True, help="SurrogateBundle to read")
    ap.add_argument("--data-dir", required=True, help="the store it was trained on")
    ap.add_argument("--out", required=True, help="where to write the bundle with its verdict classifier")
    ap.add_argument("--split", default="train", help="records the verdict classifier is fitted on")
    ap.add_argument("--check-split", default="val", help="records the verdicts are reported on ('' : none)")
    ap.add_argument("--noise", type=float, default=0.01, help="relative current noise of the fitting records")
    ap.add_argument("--seed", type=int, default=11, help="seeds the noise draw")
    ap.add_argument("--max-missed-fault-rate", type=float, default=None,
                    help="raise the verdict threshold until at most this fraction of the fitting faults pass")
    ap.add_argument("--threads", type=int, default=1)
    args = ap.parse_args()
    if not args.noise >= 0:
        raise ValueError(f"--noise must be >= 0, got {args.noise!r}")
    torch.set_num_threads(args.threads)
    bundle = SurrogateBundle.load(args.bundle)
    t0 = time.perf_counter()
    samples, scale, healthy = read_samples(bundle, args.data_dir, args.split)
    spec = bundle.classifier
    bundle.verdict_classifier = fit_verdict_classifier(
        build_classifier(spec.name, **spec.get_params()), lambda s, level: bundle.fdi(s, noise=level),
        samples, scale, healthy, args.noise, args.seed, args.max_missed_fault_rate)
    fit_s = time.perf_counter() - t0
    bundle.save(args.out)
    report = {"bundle": args.bundle, "out": args.out, "split": args.split, "n": len(healthy),
              "noise": args.noise, "max_missed_fault_rate": args.max_missed_fault_rate, "fit_s": round(fit_s, 1)}
    if args.check_split:
        report[args.check_split] = verdicts(bundle, args.data_dir, args.check_split)
    print(json.dumps(report, indent=2))


if __name__ == "__main__":
    main()
