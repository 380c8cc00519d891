"""Train and calibrate the near-nominal FDI of a pipeline for life tracking (phm_torch/tracking/near_nominal.py).

Training rows: the records of a life split (run-to-failure histories, their noise as recorded) but a held-out share
of its actuators, and the near-nominal records of a store's train split (every damage at most --max-damage, a fresh
draw of --noise white noise every 2,000 steps); inputs are the pipeline's own gappy coefficients of the selected
samples. The held-out actuators calibrate the 90 % half-widths per component and give the error reported. Writes
``<out>`` (``phm-track near_nominal=auto`` reads ``<pipeline stem>.near_nominal.pt`` beside the pipeline) and prints
JSON.

    python scripts/fit_near_nominal.py --pipeline pretrained/online_surrogates_best.pt --life /tmp/lifetrain/life \
        --store /tmp/paper40k --out pretrained/online_surrogates_best.near_nominal.pt
"""

from __future__ import annotations

import argparse
import csv
import json
import time
from pathlib import Path

import h5py
import numpy as np
import torch

from phm_torch import provenance
from phm_torch.faults import FAULT_NAMES
from phm_torch.online.loaded import load_pipeline
from phm_torch.tracking.near_nominal import PHASE_INDEX, NearNominalFDI, fit_near_nominal
from phm_torch.tracking.response import probe_k_hat


def life_records(root: Path, model) -> tuple[np.ndarray, np.ndarray, np.ndarray, list[str]]:
    """(samples (N, n_w), the pipeline's noise level (N,), k (N, 8), actuator of each row) of every inspection of a
    life split."""
    idx = model.gappy.indices.numpy()
    truth = json.loads((root / "truth.json").read_text())["actuators"]
    samples, noise, k, who = [], [], [], []
    for actuator, info in truth.items():
        for ins in info["inspections"]:
            with open(root / ins["file"]) as fh:
                column = next(csv.reader(fh)).index("current")
            current = np.loadtxt(root / ins["file"], delimiter=",", skiprows=1, usecols=column, dtype=np.float64)
            samples.append(current[idx])
            with torch.no_grad():
                noise.append(float(model.noise_level(torch.as_tensor(current, dtype=model.times.dtype)[None])[0]))
            k.append(ins["k_true"])
            who.append(actuator)
    return np.array(samples), np.array(noise), np.array(k), who


def store_records(store: Path, idx: np.ndarray, nominal: np.ndarray, max_damage: float) -> tuple[np.ndarray, ...]:
    """(samples, record RMS, k) of the store's train records whose every damage is at most ``max_damage``."""
    with h5py.File(store / "dataset.h5", "r") as f:
        k = f["train"]["K"][:]
        damage = np.abs(k - nominal)
        damage[:, PHASE_INDEX] = 0.0
        keep = np.where(damage.max(1) <= max_damage)[0]
        samples, scale = [], []
        current = f["train"]["current"]
        for start in range(0, k.shape[0], 4000):
            rows = keep[(keep >= start) & (keep < start + 4000)] - start
            block = current[start : start + 4000][rows].astype(np.float64)
            samples.append(block[:, idx])
            scale.append(np.sqrt((block**2).mean(1)))
    return np.concatenate(samples), np.concatenate(scale), k[keep]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--pipeline", required=True)
    ap.add_argument("--life", required=True, help="a life split's folder (index.csv, truth.json, the records)")
    ap.add_argument("--store", required=True, help="a store of the pipeline's actuator and command (dataset.h5)")
    ap.add_argument("--out", required=True)
    ap.add_argument("--max-damage", type=float, default=0.2)
    ap.add_argument("--noise", type=float, default=0.01, help="relative white noise added to the store's records")
    ap.add_argument("--holdout", type=int, default=5, help="every n-th actuator of the life split calibrates")
    ap.add_argument("--steps", type=int, default=40000)
    ap.add_argument("--gate", type=float, default=0.25)
    ap.add_argument("--noise-max", type=float, default=0.02)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--threads", type=int, default=2)
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    t0 = time.perf_counter()
    loaded = load_pipeline(args.pipeline)
    model = loaded.module
    idx = model.gappy.indices.numpy()
    nominal = model.nominal.double().numpy()
    life_s, life_noise, life_k, who = life_records(Path(args.life), model)
    actuators = sorted(set(who))
    held = {a for i, a in enumerate(actuators) if i % args.holdout == 0}
    cal = np.array([a in held for a in who])
    store_s, store_scale, store_k = store_records(Path(args.store), idx, nominal, args.max_damage)
    read_s = time.perf_counter() - t0

    def alpha(samples: np.ndarray) -> torch.Tensor:
        with torch.no_grad():
            x = torch.as_tensor(samples, dtype=model.gappy.modes_hat.dtype)
            return torch.cat([model.gappy(b)[0] for b in x.split(4096)]).double()

    gen = np.random.default_rng(args.seed)
    life_a = alpha(life_s[~cal])
    life_kt = torch.as_tensor(life_k[~cal])
    store_kt = torch.as_tensor(store_k)

    def fresh() -> tuple[torch.Tensor, torch.Tensor]:
        noisy = store_s + args.noise * store_scale[:, None] * gen.standard_normal(store_s.shape)
        return torch.cat([alpha(noisy), life_a]), torch.cat([store_kt, life_kt])

    net = NearNominalFDI(
        int(model.gappy.modes_hat.shape[1]), nominal=nominal.tolist(), gate=args.gate, noise_max=args.noise_max
    )
    a0, k0 = fresh()
    t1 = time.perf_counter()
    fit_near_nominal(net, a0, k0, steps=args.steps, seed=args.seed, fresh=fresh)
    fit_s = time.perf_counter() - t1
    with torch.no_grad():  # the pipeline's own estimates of the held-out records: the gate
        held_s = torch.as_tensor(life_s[cal], dtype=model.gappy.modes_hat.dtype)
        held_n = torch.as_tensor(life_noise[cal], dtype=model.times.dtype)
        k_pipeline = model(held_s, held_n)[0].double()
    rms, n_gated = net.calibrate(alpha(life_s[cal]), torch.as_tensor(life_k[cal]), k_pipeline, held_n.double())
    recorded = loaded.metadata.get("provenance") or {}
    net.provenance = {
        "source": args.pipeline,
        "probe_k_hat": probe_k_hat(model),
        "actuator": provenance.describe(recorded.get("actuator")),
        "command": provenance.describe(recorded.get("command")),
        "life_split": str(args.life),
        "life_records": int((~cal).sum()),
        "calibration_records": int(cal.sum()),
        "calibration_records_gated": n_gated,
        "calibration_actuators": len(held),
        "store": str(args.store),
        "store_records": int(store_k.shape[0]),
        "max_damage": args.max_damage,
        "noise": args.noise,
        "steps": args.steps,
        "heldout_rms": dict(zip(FAULT_NAMES, rms.tolist())),
    }
    net.save(args.out)
    print(
        json.dumps({**net.provenance, "read_s": round(read_s, 1), "fit_s": round(fit_s, 1), "out": args.out}, indent=1)
    )


if __name__ == "__main__":
    main()
