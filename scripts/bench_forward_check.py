"""Measure the consistency check (analysis by synthesis): false rejections, the corruptions it catches that
the other OOD checks miss, and its cost per record; writes a JSON report.

The fdi_band-like split (``--split``, default val) is cut in two: the first ``--calibrate`` records calibrate
the thresholds (as phm-evaluate does on its fdi_band split), the rest are the clean test records (0-3 % white
noise) and the base of the corruptions (at ``--noise``): the current shifted 10 ms against its command, its sign
flipped, reversed in time, doubled, offset by +0.2 A, and (``--other-store``) the records of another actuator.

    python scripts/bench_forward_check.py --bundle results/train/surrogates.pt --data-dir data/paper \
        [--other-store /tmp/gear] --out scripts/bench_forward_check.json
"""

from __future__ import annotations

import argparse
import json
import time

import numpy as np
import torch
from hydra.utils import instantiate
from omegaconf import OmegaConf

from phm_torch.data import DatasetStore
from phm_torch.data.store import recorded_actuator
from phm_torch.io.atomic import atomic_open
from phm_torch.online import OnlinePipeline
from phm_torch.online.consistency import calibrate_consistency
from phm_torch.surrogates import SurrogateBundle, add_noise, rms

LEVELS = (0.01, 0.03, 0.1)


def read(data_dir: str, split: str) -> torch.Tensor:
    with DatasetStore(data_dir) as store:
        return torch.as_tensor(np.asarray(store.split(split).current[()]), dtype=torch.float32)


def corruptions(x: torch.Tensor, sample_rate: float) -> dict[str, torch.Tensor]:
    lag = round(0.010 * sample_rate)
    return {
        "shift_10ms": torch.cat([x[:, :1].expand(-1, lag), x[:, :-lag]], 1),
        "sign_flip": -x,
        "time_reversal": x.flip(1),
        "gain_2x": 2.0 * x,
        "offset_0.2A": x + 0.2,
    }


@torch.no_grad()
def flags(with_check: OnlinePipeline, without: OnlinePipeline, x: torch.Tensor) -> dict[str, float]:
    ood = with_check(x)[3]
    before = without(x)[3]
    n = max(1, int((~before).sum()))
    return {
        "ood_before": float(before.double().mean()),
        "ood_with_check": float(ood.double().mean()),
        "caught_of_missed": float((ood & ~before).sum()) / n,
        "selected_samples_caught_of_missed": float(
            (
                (with_check.consistency(x.index_select(1, with_check.gappy.indices), with_check.noise_level(x)) > 1)
                & ~before
            ).sum()
        )
        / n,
    }


@torch.no_grad()
def cost_us(pipe: OnlinePipeline, x: torch.Tensor, repeats: int = 5) -> float:
    best = float("inf")
    for _ in range(repeats):
        t0 = time.perf_counter()
        pipe(x)
        best = min(best, time.perf_counter() - t0)
    return best / x.shape[0] * 1e6


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--bundle", required=True)
    ap.add_argument("--data-dir", required=True)
    ap.add_argument("--split", default="val")
    ap.add_argument("--calibrate", type=int, default=150, help="records of the split that calibrate the thresholds")
    ap.add_argument("--noise", type=float, default=0.01, help="relative noise of the corrupted records")
    ap.add_argument("--quantile", type=float, default=0.995)
    ap.add_argument("--other-store", default=None, help="a store of another actuator, same command (its val split)")
    ap.add_argument("--out", default="scripts/bench_forward_check.json")
    args = ap.parse_args()
    torch.set_num_threads(1)
    bundle = SurrogateBundle.load(args.bundle)
    if bundle.forward_model is None:
        raise ValueError(f"--bundle {args.bundle}: no forward surrogate (scripts/fit_forward_check.py adds one)")
    with DatasetStore(args.data_dir) as store:
        nominal = list(recorded_actuator(store.metadata).nominal_faults)
    damage = instantiate(OmegaConf.load("conf/damage/coupled.yaml"), nominal=nominal)
    make = {"damage": damage, "deltas": torch.zeros(3), "direction": torch.ones(8)}
    pipe = OnlinePipeline.from_bundle(bundle, **make).eval()
    bundle.forward_model, fwd = None, bundle.forward_model
    plain = OnlinePipeline.from_bundle(bundle, **make).eval()
    bundle.forward_model = fwd
    x = read(args.data_dir, args.split)
    cal, test = x[: args.calibrate], x[args.calibrate :]
    report = {
        "bundle": args.bundle,
        "data_dir": args.data_dir,
        "n_calibrate": len(cal),
        "n_test": len(test),
        "calibration": calibrate_consistency(pipe, cal, list(LEVELS), 0, args.quantile),
        "clean": {},
    }
    g = torch.Generator().manual_seed(1)
    for level in (0.0, 0.01, 0.02, 0.03, 0.1):
        noisy = add_noise(test, rms(test), level, g) if level else test
        report["clean"][f"{level:g}"] = flags(pipe, plain, noisy)
    base = add_noise(test, rms(test), args.noise, g)
    report["corruptions"] = {
        name: flags(pipe, plain, c) for name, c in corruptions(base, float(bundle.sample_rate)).items()
    }
    if args.other_store:
        other = read(args.other_store, "val")
        report["corruptions"]["other_actuator"] = flags(pipe, plain, add_noise(other, rms(other), args.noise, g))
    batch = base[:256]
    report["cost_us_per_record"] = {
        "with_check": cost_us(pipe, batch),
        "without": cost_us(plain, batch),
        "batch": len(batch),
        "threads": 1,
    }
    report["cost_us_per_record"]["check"] = (
        report["cost_us_per_record"]["with_check"] - report["cost_us_per_record"]["without"]
    )
    with atomic_open(args.out, "w") as fh:
        json.dump(report, fh, indent=2)
    print(json.dumps(report, indent=2))


if __name__ == "__main__":
    main()
