"""Give a trained surrogate bundle a forward surrogate (the online consistency check), without retraining.

``phm-train`` fits one (``forward_check=true``, the default) after the FDI network; this script does the same
for a bundle that lacks one (or replaces it), from the store the bundle was trained on: the fault vectors and
records of ``--split`` (their full POD projections the targets, each record weighted by 1 / its mean square),
the residual floors at the bundle's own FDI estimates of the held-out rows
(:func:`phm_torch.surrogates.forward.fit_forward_check`). The split is read whole (float32: 40 kB a record).
Then run phm-evaluate with the new bundle: it calibrates the thresholds (rul_calibration.json, the pipeline).

    python scripts/fit_forward_check.py --bundle results/train/surrogates.pt --data-dir data/paper \
        --out results/train/surrogates_forward.pt [--split train] [--seed 13]
"""

from __future__ import annotations

import argparse
import json
import time

import numpy as np
import torch

from phm_torch.data import DatasetStore
from phm_torch.data.store import recorded_actuator
from phm_torch.surrogates import SurrogateBundle
from phm_torch.surrogates.forward import fit_forward_check


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--bundle", required=True, help="SurrogateBundle to read")
    ap.add_argument("--data-dir", required=True, help="the store it was trained on")
    ap.add_argument("--out", required=True, help="where to write the bundle with its forward surrogate")
    ap.add_argument("--split", default="train", help="records the forward surrogate is fitted on")
    ap.add_argument("--seed", type=int, default=13, help="initialisation, shuffling and held-out draw")
    ap.add_argument("--n-hidden", type=int, default=64)
    ap.add_argument("--max-epochs", type=int, default=600)
    ap.add_argument("--threads", type=int, default=1)
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    bundle = SurrogateBundle.load(args.bundle)
    with DatasetStore(args.data_dir) as store:
        bundle.check_store(store.provenance, f"store {args.data_dir}")
        view = store.split(args.split)  # a ValueError naming the store's splits if it has no such split
        k = torch.as_tensor(np.asarray(view.K[()]), dtype=torch.float32)
        current = torch.as_tensor(np.asarray(view.current[()]), dtype=bundle.pod.mean_.dtype)
        params = recorded_actuator(store.metadata)
    if len(k) < 10:
        raise ValueError(f"split {args.split!r} of {args.data_dir!r} has {len(k)} records, at least 10 needed")
    nominal = torch.tensor(params.nominal_faults) if params is not None else None
    t0 = time.perf_counter()
    bundle.forward_model = fit_forward_check(
        bundle.pod,
        bundle.gappy,
        bundle.network,
        k,
        current,
        nominal,
        args.seed,
        n_hidden=args.n_hidden,
        max_epochs=args.max_epochs,
    )
    bundle.save(args.out)
    print(
        json.dumps(
            {
                "bundle": args.bundle,
                "out": args.out,
                "split": args.split,
                "n": len(k),
                "fit_s": round(time.perf_counter() - t0, 1),
                **bundle.forward_model.summary(),
            },
            indent=2,
        )
    )


if __name__ == "__main__":
    main()
