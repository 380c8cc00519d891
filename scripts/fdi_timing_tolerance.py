"""How trained surrogates read a current whose trigger is off by a fraction of a millisecond; writes JSON.

Each ``--bundle`` (phm-train's surrogates.pt) reads the store's val records moved by each of ``--shifts`` samples
(positive: the current late, ``x[i - shift]``, the end values held), with ``--noise`` relative white noise, through
:func:`phm_torch.surrogates.model_mismatch.mismatch_metrics`: err_k, the verdict's accuracy, missed faults and false
alarms, and the mean move of each k_hat component from its reading on time. Compare a bundle trained on records on
time with one trained with ``model.augment.max_shift`` (docs/surrogates.md, "A timing-tolerant FDI").

    python scripts/fdi_timing_tolerance.py --data-dir data/quick --bundle results/train/surrogates.pt \
        --bundle results/train_shift/surrogates.pt [--shifts 0 4 10 20 40 -20] [--out results/fdi_timing.json]
"""

from __future__ import annotations

import argparse
import json
import platform
import time
from pathlib import Path
from typing import Any

import torch

from phm_torch.data import DatasetStore
from phm_torch.drive_range import drive_bound, within_drive_range
from phm_torch.faults import FAULT_NAMES
from phm_torch.io.atomic import write_json
from phm_torch.online.corruptions import delayed
from phm_torch.surrogates import SurrogateBundle
from phm_torch.surrogates.augment import add_noise, noise_level, rms
from phm_torch.surrogates.model_mismatch import mismatch_metrics


def read_bundle(path: Path, k: torch.Tensor, healthy: torch.Tensor, clean: torch.Tensor, shifts: list[int]) -> dict:
    """One bundle's figures at every shift, and each component's mean k_hat move from the reading on time."""
    bundle = SurrogateBundle.load(path)
    dtype = bundle.pod.mean_.dtype

    def k_hat(x: torch.Tensor) -> torch.Tensor:
        with torch.no_grad():
            found = bundle.diagnose(bundle.compress(x.to(dtype)), noise=noise_level(x).to(dtype))
        return found["k_hat"].double()

    on_time = k_hat(clean)
    out: dict[str, Any] = {}
    for shift in shifts:
        moved = torch.stack([delayed(x, shift) for x in clean])
        figures = mismatch_metrics(bundle, k, healthy, clean, moved)
        move = (k_hat(moved) - on_time).mean(0)
        out[str(shift)] = {**figures, "k_hat_mean_move": dict(zip(FAULT_NAMES, move.tolist()))}
        print(json.dumps({"bundle": str(path), "shift": shift, "err_k": figures["err_k"]}), flush=True)
    return out


def main(argv: list[str] | None = None) -> dict[str, Any]:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data-dir", type=Path, required=True)
    ap.add_argument("--bundle", type=Path, action="append", required=True)
    ap.add_argument("--shifts", type=int, nargs="+", default=[0, 4, 10, 20, 40, -20])
    ap.add_argument("--noise", type=float, default=0.01, help="relative white noise of the records")
    ap.add_argument("--drive-range", type=float, default=2.0, help="x the actuator's current_limit, as phm-train")
    ap.add_argument("--out", type=Path, default=Path("results/fdi_timing_tolerance.json"))
    args = ap.parse_args(argv)
    if args.noise < 0:
        raise ValueError(f"--noise must be >= 0, got {args.noise}")
    torch.set_num_threads(2)
    start = time.perf_counter()
    with DatasetStore(args.data_dir) as store:
        view = store.split("val")
        current = torch.as_tensor(view.current[()], dtype=torch.float64)
        k = torch.as_tensor(view.K[()], dtype=torch.float64)
        healthy = torch.as_tensor(view.healthy[()]).bool()
        bound = drive_bound((store.provenance or {}).get("actuator"), args.drive_range)
    inside = within_drive_range(current, bound)  # as phm-train, records a protected drive would not have finished out
    current, k, healthy = current[inside], k[inside], healthy[inside]
    g = torch.Generator().manual_seed(0)
    clean = add_noise(current, rms(current), args.noise, g)
    report: dict[str, Any] = {
        "data_dir": str(args.data_dir),
        "records": len(k),
        "noise": args.noise,
        "shifts_samples": args.shifts,
        "bundles": {str(p): read_bundle(p, k, healthy, clean, args.shifts) for p in args.bundle},
        "wall_s": round(time.perf_counter() - start, 1),
        "machine": {"platform": platform.platform()},
    }
    write_json(args.out, report)
    print(f"wrote {args.out}")
    return report


if __name__ == "__main__":
    main()
