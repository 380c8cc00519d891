"""How far each deployment format of a pipeline is from its TorchScript file, beside how far that float32 file is from
the same pipeline evaluated in float64: the rounding floor any float32 runtime works at. Writes JSON.

Records: the pipeline's probe records (clean, 3 missing samples, OOD, ...; seeds 4-7) and the corruption suite's
val-like records (random fault vectors drawn as the paper's store draws them, HF-simulated for the pipeline's own
actuator and command, cached; 0 and 3 % current noise). A complete-records-only format (onnx, executorch) is
compared on the complete records. Per format and output: the largest |format - file| / max(1, |file|) (relative
above 1: the RUL in hours), how many records exceed 1e-5, and the same for |file - float64|; and each format against
the pipeline evaluated in float64 (what a file written with ``phm-export dtype=float64`` is made from).

    python scripts/format_equality.py --pipeline pretrained/online_surrogates_best.pt \
        --model /tmp/x/online.aoti.pt2 --model /tmp/x/online.onnx.zip --model /tmp/x64/online.onnx.zip \
        --out results/format_equality.json
"""

from __future__ import annotations

import argparse
import copy
import json
import platform
from pathlib import Path

import numpy as np
import torch

from phm_torch.io.atomic import atomic_open
from phm_torch.online.corruption_suite import CACHE, clean_records
from phm_torch.online.from_torchscript import pipeline_from_torchscript, probe_records
from phm_torch.online.loaded import as_loaded, load_pipeline
from phm_torch.online.output_diffs import scaled_differences

OUTPUTS = ("k_hat", "score", "p_faulty", "rul", "residual", "noise")
LIMIT = 1e-5


def compare(a, b, x: torch.Tensor) -> dict[str, dict[str, float]]:
    ra, rb = a.run(x), b.run(x)  # each converts x to its own dtype
    out = {}
    for name in OUTPUTS:
        va, vb = getattr(ra, name), getattr(rb, name)
        if va is None or vb is None:
            continue
        d = scaled_differences(va, vb)
        out[name] = {"max": float(d.max()), "records_over_1e-5": int((d > LIMIT).sum())}
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--pipeline", required=True, help="the TorchScript pipeline file (the reference)")
    ap.add_argument("--model", action="append", default=[], help="another format's file; repeat")
    ap.add_argument("--vectors", type=int, default=125, help="val-like fault vectors (each at 0 and 3 %% noise)")
    ap.add_argument("--out", default="results/format_equality.json")
    args = ap.parse_args()
    torch.set_num_threads(1)
    path = Path(args.pipeline)
    file = load_pipeline(path)
    eager, _ = pipeline_from_torchscript(path)
    f64 = as_loaded(copy.deepcopy(eager).double())
    cases = clean_records(eager, path, n=args.vectors, cache=CACHE)
    levels = np.repeat([0.0, 0.01, 0.02, 0.03], 2 * args.vectors)  # clean_records' order: level, twice, vectors
    keep = [c.record.current for c, lv in zip(cases, levels) if lv in (0.0, 0.03)]
    val_like = torch.stack([torch.as_tensor(r, dtype=torch.float32) for r in keep])
    x = torch.cat([*(probe_records(eager, seed=s) for s in range(4, 8)), val_like])
    complete = x[torch.isfinite(x).all(1)]
    report = {
        "pipeline": str(path),
        "records": {"all": int(x.shape[0]), "complete": int(complete.shape[0]), "val_like": int(val_like.shape[0])},
        "limit": LIMIT,
        "file_vs_float64": compare(file, f64, x),
        "formats": {},
        "machine": {"platform": platform.platform(), "torch": torch.__version__},
    }
    with torch.no_grad():
        for model_path in args.model:
            model = load_pipeline(model_path)
            served = x if bool(getattr(model, "missing_samples", True)) else complete
            wide = model.dtype == torch.float64
            report["formats"][model.format + ("_float64" if wide else "")] = {
                "file": model_path,
                "records": int(served.shape[0]),
                "dtype": str(model.dtype).removeprefix("torch."),
                "vs_file": compare(model, file, served),
                # a float64 file (phm-export dtype=float64) against the pipeline it was made from, float64 eager
                "vs_float64": compare(model, f64, served),
            }
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    with atomic_open(out, "w") as fh:
        fh.write(json.dumps(report, indent=2))
    print(json.dumps(report, indent=2))


if __name__ == "__main__":
    main()
