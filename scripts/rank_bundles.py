"""Rank surrogate bundles by err_k on a large held-out split, with bootstrap intervals and paired differences.

A 500-signal val split pins err_k down only to about +/- 0.75 points (most of the squared error sits in
the few signals with several heavy faults), so two runs closer than that cannot be ranked on it. This
script runs each bundle's online FDI (gappy POD of the selected samples, the network told each record's
estimated noise level) on every record of a split, reads them in row blocks, and reports per bundle:
err_k, its percentile-bootstrap 95 % interval, err_k per number of heavy faults (0 / 1 / 2 / 3+), and the
paired bootstrap difference of each bundle against the first (same resampled signals for both, so the
spread shared by the two cancels); and the verdict on the estimates (``bundle.verdict_healthy``):
accuracy, missed faults, false alarms, and the records only one of the two bundles judges right, with the
exact McNemar p-value against the first. The statistics are :mod:`phm_torch.surrogates.compare`'s. An independent
evaluation store of 4,000 val signals takes about a minute of HF simulation on one core:

    phm-generate experiment=paper_eval data_dir=data/paper_eval
    python scripts/rank_bundles.py --data-dir data/paper_eval --bundle 40k=results/a/surrogates.pt \
        --bundle 80k=results/b/surrogates.pt [--split val] [--noise 0.01] [--out results/rank_bundles.json]
"""

from __future__ import annotations

import argparse
import platform
import time

import torch

from phm_torch.io.atomic import write_json
from phm_torch.surrogates.bundle_specs import load_named_bundles
from phm_torch.surrogates.compare import ranking, squared_errors, verdict_table


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data-dir", required=True)
    ap.add_argument(
        "--bundle", action="append", required=True, help="[name=]path of a SurrogateBundle (first = reference)"
    )
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
    report = {
        "data_dir": args.data_dir,
        "split": args.split,
        "noise": args.noise,
        "bundles": dict(zip(bundles, args.bundle)),
        "ranking": ranking(sq, counts, args.seed),
        "verdict": verdict_table(verdicts, healthy),
        "wall_s": round(time.perf_counter() - t0, 1),
        "machine": {"platform": platform.platform(), "threads": args.threads},
    }
    for name in bundles:
        row = report["ranking"][name]
        diff = next(
            (f", {k} {v[1]:+.2f} [{v[0]:+.2f}, {v[2]:+.2f}] pp" for k, v in row.items() if k.startswith("minus_")), ""
        )
        v = report["verdict"][name]
        vs = f", McNemar p {v['mcnemar_p']:.3g}" if "mcnemar_p" in v else ""
        print(
            f"{name:>12}: err_k {row['err_k_pct']:.2f} % [{row['ci95_pct'][0]:.2f}, {row['ci95_pct'][1]:.2f}]{diff}; "
            f"verdict {100 * v['accuracy']:.2f} %, missed faults {100 * v['missed_fault_rate']:.2f} %{vs}"
        )
    write_json(args.out, report)


if __name__ == "__main__":
    main()
