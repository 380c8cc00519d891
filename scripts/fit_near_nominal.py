r"""Train and calibrate the near-nominal FDI of a pipeline for life tracking (phm_torch/tracking/near_nominal.py).

A thin command line over :func:`phm_torch.tracking.near_nominal_training.train_near_nominal` (its module docstring
says what the rows and the calibration are); phm-run's ``companions`` stage calls the same function. Writes
``<out>`` (``phm-track near_nominal=auto`` reads ``<pipeline stem>.near_nominal.pt`` beside the pipeline) and prints
JSON. The shipped file was made with (pretrained/README.md):

    python scripts/fit_near_nominal.py --pipeline pretrained/online_surrogates_best.pt --life /tmp/lifetrain/life \
        --store /tmp/nearstore --store-split rul --full-record 64 --width-factor 1.25 \
        --out pretrained/online_surrogates_best.near_nominal.pt

(64 and 1.25 are now the defaults.)
"""

from __future__ import annotations

import argparse
import json
import time

import torch

from phm_torch.tracking.near_nominal_training import NearNominalTraining, train_near_nominal

DEFAULTS = NearNominalTraining()  # the defaults are the library's (64 whole-record directions, half-widths x 1.25)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--pipeline", required=True)
    ap.add_argument("--life", required=True, help="a life split's folder (index.csv, truth.json, the records)")
    ap.add_argument("--store", help="a store of the pipeline's actuator and command (dataset.h5); optional")
    ap.add_argument(
        "--store-split",
        default=DEFAULTS.store_split,
        help="the store's split to read (rul: a store made with n_rul=8000 rul_radius=0.2 is all near nominal)",
    )
    ap.add_argument(
        "--full-record",
        type=int,
        default=DEFAULTS.full_record,
        metavar="N_MODES",
        help="read every sample of the record on its own basis of N_MODES principal directions of the training "
        "records (0: the pipeline's gappy coefficients of its selected samples)",
    )
    ap.add_argument("--out", required=True)
    ap.add_argument("--max-damage", type=float, default=DEFAULTS.max_damage)
    ap.add_argument(
        "--noise-levels",
        default=",".join(str(v) for v in DEFAULTS.noise_levels),
        help="the calibrated relative noise levels",
    )
    ap.add_argument(
        "--holdout", type=int, default=DEFAULTS.holdout, help="every n-th actuator of the life split calibrates"
    )
    ap.add_argument("--steps", type=int, default=DEFAULTS.steps)
    ap.add_argument("--gate", type=float, default=DEFAULTS.gate)
    ap.add_argument(
        "--width-factor",
        type=float,
        default=DEFAULTS.width_factor,
        help="multiplies the calibrated half-widths: the held-out errors persist from one inspection to the next, "
        "which the filter fuses as independent; choose it on the tracker's coverage of held-out histories",
    )
    ap.add_argument("--seed", type=int, default=DEFAULTS.seed)
    ap.add_argument("--threads", type=int, default=2)
    args = ap.parse_args()
    if not args.width_factor >= 1.0:
        ap.error(f"--width-factor must be >= 1, got {args.width_factor}")
    try:
        settings = NearNominalTraining(
            full_record=args.full_record,
            max_damage=args.max_damage,
            noise_levels=tuple(float(v) for v in args.noise_levels.split(",")),
            holdout=args.holdout,
            steps=args.steps,
            gate=args.gate,
            width_factor=args.width_factor,
            seed=args.seed,
            store_split=args.store_split,
        )
    except ValueError as err:
        ap.error(str(err))
    torch.set_num_threads(args.threads)
    t0 = time.perf_counter()
    try:
        net, report = train_near_nominal(args.pipeline, args.life, settings, args.store)
    except ValueError as err:  # a life split or store that cannot be read: the input and its value
        ap.error(str(err))
    net.save(args.out)
    print(json.dumps({**report, "wall_s": round(time.perf_counter() - t0, 1), "out": args.out}, indent=1))


if __name__ == "__main__":
    main()
