"""Give an exported TorchScript pipeline that lacks one the consistency check (analysis by synthesis), from a store.

Pipelines exported before the check, the shipped pretrained one among them, answer a record their FDI cannot
reproduce (a probe at twice its range, a reversed current) as confidently as any other. This script fits the
forward surrogate k -> POD coefficients on a store of the pipeline's actuator and command
(:func:`phm_torch.online.pipeline_consistency.attach_consistency`: the basis comes from the pipeline itself, so its
bundle is not needed) on the first ``--fit-records`` training records, calibrates its thresholds on the next
``--calibrate-records`` with white noise at the pipeline's interval noise levels
(:func:`phm_torch.online.consistency.calibrate_consistency`, as phm-evaluate does), and writes the pipeline with
its metadata kept. Everything else in the pipeline is unchanged.

    python scripts/add_consistency_check.py --pipeline pretrained/online_surrogates_best.pt \
        --data-dir data/paper40k --out /tmp/cc/online.pt
    phm-export pipeline=/tmp/cc/online.pt format=[torchscript,export] out=/tmp/cc2/online_surrogates_best.pt
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np
import torch

from phm_torch import provenance
from phm_torch.data import DatasetStore
from phm_torch.data.store import recorded_actuator
from phm_torch.online.consistency import DEFAULT_QUANTILE, calibrate_consistency, consistency_statistics
from phm_torch.online.export import export_torchscript
from phm_torch.online.from_torchscript import pipeline_from_torchscript
from phm_torch.online.pipeline_consistency import attach_consistency
from phm_torch.pipelines.evaluate.calibration import noisy


def _rows(store: DatasetStore, split: str, start: int, stop: int) -> tuple[torch.Tensor, torch.Tensor]:
    view = store.split(split)
    stop = min(stop, len(view))
    if stop - start < 10:
        raise ValueError(f"split {split!r} has {len(view)} records: too few for rows {start}..{stop}")
    return (
        torch.as_tensor(np.asarray(view.K[start:stop]), dtype=torch.float32),
        torch.as_tensor(np.asarray(view.current[start:stop]), dtype=torch.float32),
    )


def _flag_rate(pipe: torch.nn.Module, x: torch.Tensor) -> dict[str, float]:
    """Share of full records flagged by the consistency check alone, and by anything."""
    full, _, level, ood = consistency_statistics(pipe, x)
    inconsistent = full > pipe.consistency_check.threshold(level, True)
    return {"inconsistent": float(inconsistent.double().mean()), "flagged": float(ood.double().mean())}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--pipeline", required=True, help="the TorchScript pipeline file")
    ap.add_argument("--data-dir", required=True, help="a store of the pipeline's actuator and command")
    ap.add_argument("--out", required=True)
    ap.add_argument("--fit-records", type=int, default=20000, help="training records the surrogate is fitted on")
    ap.add_argument("--calibrate-records", type=int, default=4000, help="the next ones, its thresholds")
    ap.add_argument("--quantile", type=float, default=DEFAULT_QUANTILE)
    ap.add_argument("--seed", type=int, default=13)
    ap.add_argument("--max-epochs", type=int, default=600)
    args = ap.parse_args()
    torch.set_num_threads(1)
    pipe, metadata = pipeline_from_torchscript(args.pipeline)
    with DatasetStore(args.data_dir) as store:
        provenance.require_same(store.provenance or {}, metadata.get("provenance") or {}, f"store {args.data_dir}")
        params = recorded_actuator(store.metadata)
        k_fit, x_fit = _rows(store, "train", 0, args.fit_records)
        _, x_cal = _rows(store, "train", args.fit_records, args.fit_records + args.calibrate_records)
        _, x_val = _rows(store, "val", 0, 10**9)
    nominal = torch.tensor(params.nominal_faults) if params is not None else None
    t0 = time.perf_counter()
    model = attach_consistency(pipe, k_fit, x_fit, nominal, args.seed, max_epochs=args.max_epochs)
    fit_s = time.perf_counter() - t0
    del x_fit
    levels = [float(v) for v in pipe.interval_noise.tolist()]
    calibration = calibrate_consistency(pipe, x_cal, levels, args.seed, args.quantile)
    val = {f"{level:g}": _flag_rate(pipe, noisy(x_val, level, args.seed + 1)) for level in (0.0, 0.01, 0.03)}
    export_torchscript(pipe, args.out, {**metadata, "consistency": calibration})
    report = {
        "out": args.out,
        "fit_records": len(k_fit),
        "calibrate_records": len(x_cal),
        "fit_s": round(fit_s, 1),
        "surrogate": model.summary(),
        "calibration": calibration,
        "val_flag_rates": val,
    }
    Path(args.out).with_suffix(".consistency.json").write_text(json.dumps(report, indent=2))
    print(json.dumps(report, indent=2))


if __name__ == "__main__":
    main()
