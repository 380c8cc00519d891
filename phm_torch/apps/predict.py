"""``phm-predict``: the exported online pipeline on measurement CSVs -> JSON (one record per file).

Each record: ``k_hat`` {fault name: value}, ``health_score`` (> 0 healthy), ``healthy``, ``p_faulty`` (the
probability that the actuator is faulty given that score, calibrated on held-out records by phm-evaluate;
``null`` out of distribution), ``rul_hours``
{p5, p50, p95} (``null`` when the input is out of distribution: never a confident RUL from garbage),
``out_of_distribution`` and the gappy ``residual`` [A]. The model is a TorchScript file written by
``phm-evaluate``/``phm_torch.online.export``; it is loaded with ``torch.jit.load`` (no unpickling).
"""

from __future__ import annotations

import json
import logging
import math
from pathlib import Path
from typing import Any

import hydra
import torch
from omegaconf import DictConfig

from ..faults import FAULT_NAMES
from ..io import read_measurement
from . import common

log = logging.getLogger(__name__)


def predict(cfg: DictConfig) -> tuple[dict[str, Any], dict[str, Any]]:
    """Run the exported pipeline ``cfg.pipeline`` on every CSV of ``cfg.measurements``."""
    paths = common.plain(cfg.measurements)
    paths = [paths] if isinstance(paths, str) else paths
    if not isinstance(paths, list) or not paths or not all(isinstance(p, str) for p in paths):
        raise ValueError(f"measurements must be a CSV path or a list of paths, got {paths!r}")
    model_path = Path(cfg.pipeline)
    if not model_path.is_file():
        raise ValueError(f"pipeline: no such file {str(model_path)!r} (export one with phm-evaluate or phm-export)")
    model = torch.jit.load(str(model_path))
    calibrated = hasattr(model, "faulty_probability")
    if not calibrated:
        log.warning("%s was exported before the verdict calibration existed: p_faulty is null", model_path)
    n_full = int(model.n_full)
    dtype = model.times.dtype
    records = []
    for path in paths:
        m = read_measurement(path, expected_rate=float(model.sample_rate), resample=bool(cfg.resample))
        current = torch.as_tensor(m.current, dtype=dtype).unsqueeze(0)
        if current.shape[1] != n_full:
            raise ValueError(f"{path}: current has {current.shape[1]} samples; the model expects {n_full} "
                             f"(the full test record)")
        with torch.no_grad():
            k_hat, score, rul, ood, resid = model(current)
            p_faulty = float(model.faulty_probability(score)[0]) if calibrated else float("nan")
        r = rul[0].tolist()
        records.append({
            "file": str(path),
            "k_hat": dict(zip(FAULT_NAMES, k_hat[0].tolist())),
            "health_score": float(score[0]), "healthy": bool(score[0] > 0),
            "p_faulty": None if bool(ood[0]) or math.isnan(p_faulty) else p_faulty,
            "rul_hours": None if any(math.isnan(v) for v in r) else dict(zip(("p5", "p50", "p95"), r)),
            "out_of_distribution": bool(ood[0]), "residual": float(resid[0]),
        })
    if cfg.out:
        common.write_json(Path(cfg.out), records)
    return {"files": len(records), "out_of_distribution": sum(r["out_of_distribution"] for r in records)}, \
        {"records": records}


@hydra.main(config_path=common.CONFIG_PATH, config_name="predict", version_base="1.3")
@common.report_errors("phm-predict")
def main(cfg: DictConfig) -> None:
    _, objects = predict(cfg)
    if not cfg.out:
        print(json.dumps(objects["records"], indent=2), flush=True)


if __name__ == "__main__":
    main()
