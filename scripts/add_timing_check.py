"""Give an exported pipeline that lacks it the ``timing`` check's threshold phm-evaluate calibrates
(``timing_ratio_max``, :mod:`phm_torch.online.timing_check`), from an independent store of its actuator and command.

The check reads a record again moved by every second sample and refuses it where the pipeline's own answer explains it
far better moved; how much better a clean record can be explained is the pipeline's own, so the check runs only for a
pipeline with its threshold. This script reads a split of a store made for the pipeline's actuator and command
(checked; make it with a seed of its own), adds white noise at the pipeline's first calibrated level (as phm-evaluate
does), keeps the records the pipeline reads in distribution, calibrates on the first ``--records`` of them with
phm-evaluate's own function and writes the pipeline again, everything else unchanged, in the formats asked for
(:func:`~phm_torch.online.from_torchscript.rewrite_pipeline`: the written files are checked against the input).

    phm-generate experiment=paper seed=77 dataset.n_train=1 dataset.n_val=2000 dataset.n_rul=1 dataset.n_labels=0 \
        data_dir=/tmp/ref_val77
    python scripts/add_timing_check.py --pipeline pretrained/online_surrogates_best.pt --data-dir /tmp/ref_val77 \
        --out /tmp/tc/online_surrogates_best.pt

Writes ``<out stem>.timing_check.json`` (the threshold, its records' ratios, the store, the noise) beside the files.
"""

from __future__ import annotations

import json
from pathlib import Path

import torch

from phm_torch import provenance
from phm_torch.data import DatasetStore
from phm_torch.drive_range import within_drive_range
from phm_torch.online.export import read_metadata
from phm_torch.online.from_torchscript import rewrite_arguments, rewrite_with_report
from phm_torch.online.timing_check import TIMING_QUANTILE, calibrate_timing_ratio
from phm_torch.pipelines.evaluate.calibration import noisy
from phm_torch.pipelines.evaluate.pipeline import TIMING_RECORDS


def measure(pipeline_path: Path, data_dir: Path, split: str, seed: int, records: int) -> dict:
    """The timing threshold of the pipeline on the first ``records`` in-distribution records of ``split`` of the
    store ``data_dir`` (noise at the pipeline's first calibrated level), with the store and the noise."""
    if records < 1:
        raise ValueError(f"--records must be >= 1, got {records}")
    module = torch.jit.load(str(pipeline_path))
    metadata = read_metadata(pipeline_path)
    if not bool(getattr(module, "has_consistency", False)):
        raise ValueError(
            f"{pipeline_path}: the pipeline has no consistency check to scan with (add_consistency_check.py)"
        )
    with DatasetStore(data_dir) as store:
        provenance.require_same(store.provenance or {}, metadata.get("provenance") or {}, f"store {data_dir}")
        if split not in store.splits:
            raise ValueError(f"split: {split!r} not in store {data_dir} (it has {sorted(store.splits)})")
        clean = torch.as_tensor(store.split(split).current[()], dtype=torch.float64)
        fingerprint = store.manifest.get("fingerprint")
    clean = clean[within_drive_range(clean, metadata.get("drive_current_bound"))]
    if not bool(torch.isfinite(module.k_half_widths).any()):
        raise ValueError(f"{pipeline_path}: no calibrated noise level (exported without phm-evaluate's calibration)")
    noise = float(module.interval_noise[0])
    signals = noisy(clean, noise, seed)
    with torch.no_grad():
        ood = module(signals.to(module.times.dtype))[3].bool()
    kept = signals[~ood][:records]
    if kept.shape[0] < 50:
        raise ValueError(f"split {split!r} of {data_dir}: {kept.shape[0]} in-distribution records, at least 50 needed")
    threshold = calibrate_timing_ratio(module, kept, float(module.sample_rate))
    return {
        "timing_ratio_max": threshold,
        "quantile": TIMING_QUANTILE,
        "records": int(kept.shape[0]),
        "store": str(data_dir),
        "store_fingerprint": fingerprint,
        "noise": noise,
        "seed": seed,
    }


def main(argv: list[str] | None = None) -> dict:
    ap = rewrite_arguments(__doc__)
    ap.add_argument("--records", type=int, default=TIMING_RECORDS, help="in-distribution records calibrated on")
    args = ap.parse_args(argv)
    torch.set_num_threads(1)
    figures = measure(args.pipeline, args.data_dir, args.split, args.seed, args.records)
    metadata = {"timing_ratio_max": figures["timing_ratio_max"]}
    report = rewrite_with_report(args.pipeline, args.out, args.formats, metadata, {**figures, "report": "timing_check"})
    print(json.dumps(report, indent=2))
    return report


if __name__ == "__main__":
    main()
