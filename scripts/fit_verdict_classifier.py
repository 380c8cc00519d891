"""Give a trained surrogate bundle a verdict classifier fitted on its own FDI estimates, without retraining.

``phm-train`` fits one (``verdict_classifier=true``, the default) right after the FDI network; this script
does the same for a bundle that lacks one (or replaces it), from the store the bundle was trained on:
the selected samples of every record of ``--split``, white noise of ``--noise`` times each record's RMS
current (the rated measurement noise, phm-train's ``eval.noise``), the bundle's FDI told that level, and
a classifier of the bundle's own kind and settings fitted on (k_hat, the records' health)
(:mod:`phm_torch.surrogates.verdict_refit`, which does the work). It reads the split in row blocks, so an
80,000-record store needs little memory, and reports the verdict on ``--check-split`` after the fit.

    python scripts/fit_verdict_classifier.py --bundle results/train/surrogates.pt --data-dir data/paper \
        --out results/train/surrogates_verdict.pt [--split train] [--noise 0.01] [--seed 11]
"""

from __future__ import annotations

import argparse
import json

import torch

from phm_torch.surrogates.verdict_refit import refit_verdict_classifier


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--bundle", required=True, help="SurrogateBundle to read")
    ap.add_argument("--data-dir", required=True, help="the store it was trained on")
    ap.add_argument("--out", required=True, help="where to write the bundle with its verdict classifier")
    ap.add_argument("--split", default="train", help="records the verdict classifier is fitted on")
    ap.add_argument("--check-split", default="val", help="records the verdicts are reported on ('' : none)")
    ap.add_argument("--noise", type=float, default=0.01, help="relative current noise of the fitting records")
    ap.add_argument("--seed", type=int, default=11, help="seeds the noise draw")
    ap.add_argument(
        "--max-missed-fault-rate",
        type=float,
        default=None,
        help="raise the verdict threshold until at most this fraction of the fitting faults pass",
    )
    ap.add_argument("--threads", type=int, default=1)
    args = ap.parse_args()
    if not args.noise >= 0:
        raise ValueError(f"--noise must be >= 0, got {args.noise!r}")
    torch.set_num_threads(args.threads)
    report = refit_verdict_classifier(
        args.bundle,
        args.data_dir,
        args.out,
        args.split,
        args.check_split,
        args.noise,
        args.seed,
        args.max_missed_fault_rate,
    )
    print(json.dumps(report, indent=2))


if __name__ == "__main__":
    main()
