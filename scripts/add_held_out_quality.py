"""Give an exported pipeline that lacks them the held-out figures phm-evaluate records: ``held_out_quality`` (how often
its verdicts of each kind were wrong) and ``identifiability`` (R^2 of each component's estimate), from an independent
store of its actuator and command.

The shipped pretrained pipeline was exported before phm-evaluate measured either, so phm-predict gave its verdicts
without ``verdict_held_out_error`` and listed no component under ``k_not_identified``. This script reads a split of
a store made for the pipeline's actuator and command (checked; make it with a seed of its own: the pipeline's files
do not record the store they were trained on), adds white noise at the pipeline's first calibrated level (as phm-evaluate
does; ``--noise`` for a pipeline exported without that calibration), runs the pipeline as exported (rebuilt eagerly from the TorchScript file), measures both with phm-evaluate's
own functions and writes the pipeline again, everything else unchanged, in the formats asked for
(:func:`~phm_torch.online.from_torchscript.rewrite_pipeline`: the written files are checked against the input).
The RUL figures of ``held_out_quality`` are left out (null): they need the rul split's reference RULs.

    phm-generate experiment=paper seed=77 dataset.n_train=1 dataset.n_val=2000 dataset.n_rul=1 dataset.n_labels=0 \
        data_dir=/tmp/ref_val77
    python scripts/add_held_out_quality.py --pipeline pretrained/online_surrogates_best.pt --data-dir /tmp/ref_val77 \
        --out /tmp/hq/online_surrogates_best.pt

Writes ``<out stem>.held_out_quality.json`` (the figures, the store, the noise) beside the files.
"""

from __future__ import annotations

import json
from pathlib import Path

import torch

from phm_torch import provenance
from phm_torch.data import DatasetStore
from phm_torch.drive_range import within_drive_range
from phm_torch.online.from_torchscript import pipeline_from_torchscript, rewrite_arguments, rewrite_with_report
from phm_torch.pipelines.evaluate.calibration import identifiability, noisy
from phm_torch.pipelines.evaluate.quality import held_out_quality


def noise_level(pipe: torch.nn.Module, noise: float | None) -> float:
    """The relative noise added to the held-out records: ``noise`` if given, else the pipeline's first calibrated
    level; a pipeline without calibrated intervals records none, and reading it noise-free would flatter it."""
    if noise is not None:
        if not noise >= 0.0:
            raise ValueError(f"--noise must be a relative noise level >= 0, got {noise!r}")
        return float(noise)
    if not bool(torch.isfinite(pipe.k_half_widths).any()):
        raise ValueError(
            "the pipeline records no calibrated noise level (exported without phm-evaluate's calibration): "
            "give --noise, e.g. --noise 0.01"
        )
    return float(pipe.interval_noise[0])


def measure(pipeline_path: Path, data_dir: Path, split: str, seed: int, noise: float | None = None) -> dict:
    """The pipeline's held-out quality and identifiability on ``split`` of the store ``data_dir``, with the store,
    the noise level and the records left out beyond the pipeline's drive range."""
    pipe, metadata = pipeline_from_torchscript(pipeline_path)
    with DatasetStore(data_dir) as store:
        provenance.require_same(store.provenance or {}, metadata.get("provenance") or {}, f"store {data_dir}")
        if split not in store.splits:
            raise ValueError(f"split: {split!r} not in store {data_dir} (it has {sorted(store.splits)})")
        view = store.split(split)
        k = torch.as_tensor(view.K[()], dtype=torch.float64)
        clean = torch.as_tensor(view.current[()], dtype=torch.float64)
        healthy = torch.as_tensor(view.healthy[()]).bool()
        fingerprint = store.manifest.get("fingerprint")
    if k.shape[0] < 50:
        raise ValueError(f"split {split!r} of {data_dir} holds {k.shape[0]} records: at least 50 are needed")
    inside = within_drive_range(clean, metadata.get("drive_current_bound"))
    k, clean, healthy = k[inside], clean[inside], healthy[inside]
    noise = noise_level(pipe, noise)
    signals = noisy(clean, noise, seed)
    with torch.no_grad():
        k_hat, _, _, ood, _ = pipe(signals.to(pipe.times.dtype))
    where = f"{split} of {data_dir}"
    return {
        "held_out_quality": held_out_quality(pipe, signals, healthy, where, {}),
        "identifiability": identifiability(k_hat.to(torch.float64), k, ood.bool()),
        "store": str(data_dir),
        "store_fingerprint": fingerprint,
        "noise": noise,
        "seed": seed,
        "beyond_drive_range": int((~inside).sum()),
    }


def main(argv: list[str] | None = None) -> dict:
    ap = rewrite_arguments(__doc__)
    ap.add_argument(
        "--noise",
        type=float,
        default=None,
        help="relative noise added (default: the pipeline's first calibrated level)",
    )
    args = ap.parse_args(argv)
    torch.set_num_threads(1)
    figures = measure(args.pipeline, args.data_dir, args.split, args.seed, args.noise)
    metadata = {"held_out_quality": figures["held_out_quality"], "identifiability": figures["identifiability"]}
    report = rewrite_with_report(
        args.pipeline, args.out, args.formats, metadata, {**figures, "report": "held_out_quality"}
    )
    print(json.dumps(report, indent=2))
    return report


if __name__ == "__main__":
    main()
