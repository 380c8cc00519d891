"""Train and calibrate the near-nominal FDI of a pipeline for life tracking (phm_torch/tracking/near_nominal.py).

Training rows: the records of a life split (run-to-failure histories) but a held-out share of its actuators, and the
near-nominal records of a store's train split (every damage at most --max-damage); every 2,000 steps each row gets a
fresh relative noise level, uniform up to 1.1 x the last of --noise-levels (a life record at least its own), and a
fresh draw of white noise to reach it. Inputs are the pipeline's own gappy coefficients of the selected samples and
the level. The held-out actuators, brought to each of --noise-levels, calibrate the 90 % half-widths per component
and level and give the errors reported. Writes
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


def life_records(
    root: Path, model, full: bool = False
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, list[str]]:
    """(samples (N, n_w), or with ``full`` the records (N, n_full); record RMS (N,), the pipeline's noise level (N,),
    k (N, 8), actuator of each row) of every inspection of a life split."""
    idx = slice(None) if full else model.gappy.indices.numpy()
    truth = json.loads((root / "truth.json").read_text())["actuators"]
    samples, scale, noise, k, who = [], [], [], [], []
    for actuator, info in truth.items():
        for ins in info["inspections"]:
            with open(root / ins["file"]) as fh:
                column = next(csv.reader(fh)).index("current")
            current = np.loadtxt(root / ins["file"], delimiter=",", skiprows=1, usecols=column, dtype=np.float64)
            samples.append(current[idx])
            scale.append(float(np.sqrt((current**2).mean())))
            with torch.no_grad():
                noise.append(float(model.noise_level(torch.as_tensor(current, dtype=model.times.dtype)[None])[0]))
            k.append(ins["k_true"])
            who.append(actuator)
    return np.array(samples), np.array(scale), np.array(noise), np.array(k), who


def store_records(
    store: Path, idx, nominal: np.ndarray, max_damage: float, split: str = "train"
) -> tuple[np.ndarray, ...]:
    """(samples, record RMS, k) of the store's ``split`` records whose every damage is at most ``max_damage``."""
    with h5py.File(store / "dataset.h5", "r") as f:
        k = f[split]["K"][:]
        damage = np.abs(k - nominal)
        damage[:, PHASE_INDEX] = 0.0
        keep = np.where(damage.max(1) <= max_damage)[0]
        samples, scale = [], []
        current = f[split]["current"]
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
    ap.add_argument("--store", help="a store of the pipeline's actuator and command (dataset.h5); optional")
    ap.add_argument(
        "--store-split",
        default="train",
        help="the store's split to read (rul: a store made with n_rul=8000 rul_radius=0.2 is all near nominal)",
    )
    ap.add_argument(
        "--full-record",
        type=int,
        default=0,
        metavar="N_MODES",
        help="read every sample of the record on its own basis of N_MODES principal directions of the training "
        "records (0: the pipeline's gappy coefficients of its selected samples)",
    )
    ap.add_argument("--out", required=True)
    ap.add_argument("--max-damage", type=float, default=0.2)
    ap.add_argument("--noise-levels", default="0.01,0.02,0.03,0.04", help="the calibrated relative noise levels")
    ap.add_argument("--holdout", type=int, default=5, help="every n-th actuator of the life split calibrates")
    ap.add_argument("--steps", type=int, default=40000)
    ap.add_argument("--gate", type=float, default=0.25)
    ap.add_argument(
        "--width-factor",
        type=float,
        default=1.0,
        help="multiplies the calibrated half-widths: the held-out errors persist from one inspection to the next, "
        "which the filter fuses as independent; choose it on the tracker's coverage of held-out histories",
    )
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--threads", type=int, default=2)
    args = ap.parse_args()
    if not args.width_factor >= 1.0:
        ap.error(f"--width-factor must be >= 1, got {args.width_factor}")
    torch.set_num_threads(args.threads)
    t0 = time.perf_counter()
    loaded = load_pipeline(args.pipeline)
    model = loaded.module
    full = args.full_record > 0
    idx = slice(None) if full else model.gappy.indices.numpy()
    nominal = model.nominal.double().numpy()
    life_s, life_scale, life_noise, life_k, who = life_records(Path(args.life), model, full)
    actuators = sorted(set(who))
    held = {a for i, a in enumerate(actuators) if i % args.holdout == 0}
    cal = np.array([a in held for a in who])
    if args.store:
        store_s, store_scale, store_k = store_records(Path(args.store), idx, nominal, args.max_damage, args.store_split)
    else:
        store_s, store_scale, store_k = np.zeros((0, life_s.shape[1])), np.zeros(0), np.zeros((0, len(FAULT_NAMES)))
    read_s = time.perf_counter() - t0
    levels = [float(v) for v in args.noise_levels.split(",")]
    net = NearNominalFDI(
        args.full_record if full else int(model.gappy.modes_hat.shape[1]),
        nominal=nominal.tolist(),
        gate=args.gate,
        noise_levels=levels,
        n_full=int(model.n_full) if full else None,
    )
    explained = None
    held_selected = life_s[cal][:, model.gappy.indices.numpy()] if full else life_s[cal]  # what the pipeline reads
    if full:  # the basis from the training rows; every row projected once: noise is then added to the coefficients,
        # white of the same std on each (orthonormal basis), as adding it to the record and projecting would
        train_rows = np.concatenate([store_s, life_s[~cal]])
        explained = net.fit_basis(torch.as_tensor(train_rows)).sum().item()
        del train_rows
        with torch.no_grad():
            life_s = net.coefficients(model, torch.as_tensor(life_s))[0].numpy()
            store_s = net.coefficients(model, torch.as_tensor(store_s))[0].numpy()

    def alpha(samples: np.ndarray) -> torch.Tensor:
        if full:
            return torch.as_tensor(samples, dtype=torch.float64)
        with torch.no_grad():
            x = torch.as_tensor(samples, dtype=model.gappy.modes_hat.dtype)
            return torch.cat([model.gappy(b)[0] for b in x.split(4096)]).double()

    gen = np.random.default_rng(args.seed)
    top = levels[-1] * 1.1

    def noisier(samples: np.ndarray, scale: np.ndarray, now: np.ndarray, target: np.ndarray) -> np.ndarray:
        """The samples with white noise added to reach the relative level ``target`` from ``now`` (per row)."""
        extra = np.sqrt(np.clip(target**2 - now**2, 0.0, None)) * scale
        return samples + extra[:, None] * gen.standard_normal(samples.shape)

    train_s, train_scale, train_now = life_s[~cal], life_scale[~cal], life_noise[~cal]
    life_kt = torch.as_tensor(life_k[~cal])
    store_kt = torch.as_tensor(store_k)

    def fresh() -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Every row at a fresh noise level, uniform up to 1.1 x the last calibrated one (life rows: at least their
        own), and a fresh draw of it."""
        store_level = gen.uniform(0.002, top, store_s.shape[0])
        life_level = np.maximum(gen.uniform(0.002, top, train_s.shape[0]), train_now)
        a = torch.cat(
            [
                alpha(noisier(store_s, store_scale, np.zeros(store_s.shape[0]), store_level)),
                alpha(noisier(train_s, train_scale, train_now, life_level)),
            ]
        )
        return a, torch.as_tensor(np.concatenate([store_level, life_level])), torch.cat([store_kt, life_kt])

    t1 = time.perf_counter()
    fit_near_nominal(net, *fresh(), steps=args.steps, seed=args.seed, fresh=fresh)
    fit_s = time.perf_counter() - t1
    held_s, held_scale, held_now, held_k = life_s[cal], life_scale[cal], life_noise[cal], torch.as_tensor(life_k[cal])
    calibration = {}
    for i, level in enumerate(levels):  # the held-out histories at each level: the pipeline's estimates gate them
        target = np.maximum(np.full(held_s.shape[0], level), held_now)
        noisy = noisier(held_s, held_scale, held_now, target)
        level_n = torch.as_tensor(target)
        with torch.no_grad():  # the pipeline's gate reads the held-out records at that level
            x = torch.as_tensor(noisier(held_selected, held_scale, held_now, target), dtype=model.gappy.modes_hat.dtype)
            k_pipeline = model(x, level_n.to(model.times.dtype))[0].double()
        rms, n_gated = net.calibrate(i, alpha(noisy), held_k, k_pipeline, level_n)
        calibration[str(level)] = {"records": n_gated, "rms": dict(zip(FAULT_NAMES, rms.tolist()))}
    net.half_widths_.mul_(args.width_factor)
    recorded = loaded.metadata.get("provenance") or {}
    net.provenance = {
        "source": args.pipeline,
        "probe_k_hat": probe_k_hat(model),
        "actuator": provenance.describe(recorded.get("actuator")),
        "command": provenance.describe(recorded.get("command")),
        "life_split": str(args.life),
        "life_records": int((~cal).sum()),
        "calibration_records": int(cal.sum()),
        "calibration_actuators": len(held),
        "store": args.store,
        "store_split": args.store_split if args.store else None,
        "store_records": int(store_k.shape[0]),
        "max_damage": args.max_damage,
        "width_factor": args.width_factor,
        "noise_levels": levels,
        "steps": args.steps,
        "input": f"full record, {args.full_record} principal directions"
        if full
        else "the pipeline's gappy coefficients",
        **({"basis_variance_fraction": explained} if full else {}),
        "heldout": calibration,
    }
    net.save(args.out)
    print(
        json.dumps({**net.provenance, "read_s": round(read_s, 1), "fit_s": round(fit_s, 1), "out": args.out}, indent=1)
    )


if __name__ == "__main__":
    main()
