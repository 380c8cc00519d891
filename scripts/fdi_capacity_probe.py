"""What a store's records carry of each fault, apart from the pipeline's choices: an FDI network trained on the POD
coefficients of the *whole* current record (no sample selection, no gappy reconstruction), at a chosen number of
modes and a chosen width; writes JSON.

The paper's FDI reads 22 modes from 30 samples with 20 neurons. When a component's R^2 is low there, this separates
"the test command does not make the fault visible" (low at every capacity) from "the pipeline's configuration does
not read it" (higher with more modes or neurons), and tells whether a configuration lever helps one actuator more than
another (run it on both stores). Records beyond the drive range (``--drive-range`` x the store actuator's
``current_limit``, as phm-train) are left out of both splits. Adam, mean-squared error on k, cosine schedule;
``--hidden`` <= 32 is one tanh layer (the paper's kind), wider is two GELU layers.

    python scripts/fdi_capacity_probe.py --data-dir data/paper --modes 22 --hidden 20 --out results/probe.json

Reports err_k (phm_torch.surrogates.metrics.err_k) and each component's R^2 on the val split, and the share of the
training records' centred energy the modes hold.
"""

from __future__ import annotations

import argparse
import json
import platform
import time

import torch

from phm_torch.data import DatasetStore
from phm_torch.drive_range import drive_bound, within_drive_range
from phm_torch.faults import FAULT_NAMES
from phm_torch.io.atomic import write_json
from phm_torch.surrogates.metrics import err_k


def network(n_in: int, hidden: int) -> torch.nn.Module:
    """One tanh layer up to 32 neurons (the paper's kind), two GELU layers above."""
    if hidden <= 32:
        return torch.nn.Sequential(torch.nn.Linear(n_in, hidden), torch.nn.Tanh(), torch.nn.Linear(hidden, 8))
    return torch.nn.Sequential(
        torch.nn.Linear(n_in, hidden),
        torch.nn.GELU(),
        torch.nn.Linear(hidden, hidden),
        torch.nn.GELU(),
        torch.nn.Linear(hidden, 8),
    )


def r_squared(k_hat: torch.Tensor, k: torch.Tensor) -> list[float]:
    return (1 - (k_hat - k).pow(2).sum(0) / (k - k.mean(0)).pow(2).sum(0)).tolist()


def probe(data_dir: str, modes: int, hidden: int, epochs: int, drive_range: float, seed: int) -> dict:
    """Train and judge one FDI on the store's train and val splits (see the module docstring)."""
    if modes < 1 or hidden < 1 or epochs < 1:
        raise ValueError(f"--modes, --hidden and --epochs must be >= 1, got {modes}, {hidden}, {epochs}")
    torch.manual_seed(seed)
    with DatasetStore(data_dir) as store:
        prov = store.provenance or {}
        bound = drive_bound(prov.get("actuator"), drive_range)
        splits = {}
        for name in ("train", "val"):
            if name not in store.splits:
                raise ValueError(f"store {data_dir} has no {name!r} split (it has {sorted(store.splits)})")
            view = store.split(name)
            x = torch.as_tensor(view.current[()], dtype=torch.float32)
            k = torch.as_tensor(view.K[()], dtype=torch.float32)
            inside = within_drive_range(x, bound)
            splits[name] = (x[inside], k[inside], int((~inside).sum()))
    (x_tr, k_tr, out_tr), (x_va, k_va, out_va) = splits["train"], splits["val"]
    mean = x_tr.mean(0)
    a_tr, a_va = (x_tr - mean).double(), (x_va - mean).double()
    _, s, v = torch.svd_lowrank(a_tr, q=min(modes + 10, min(a_tr.shape)), niter=4)
    v = v[:, :modes]
    energy = float(s[:modes].pow(2).sum() / a_tr.pow(2).sum())
    f_tr, f_va = (a_tr @ v).float(), (a_va @ v).float()
    centre, scale = f_tr.mean(0), f_tr.std(0) + 1e-6
    f_tr, f_va = (f_tr - centre) / scale, (f_va - centre) / scale
    net = network(modes, hidden)
    opt = torch.optim.AdamW(net.parameters(), 1e-3, weight_decay=1e-4)
    sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, epochs)
    for _ in range(epochs):
        for rows in torch.randperm(len(f_tr)).split(256):
            loss = (net(f_tr[rows]) - k_tr[rows]).pow(2).mean()
            opt.zero_grad()
            loss.backward()
            opt.step()
        sched.step()
    with torch.no_grad():
        k_hat = net(f_va).clamp(0, 1).double()
    return {
        "err_k": err_k(k_hat, k_va.double()),
        "r2": dict(zip(FAULT_NAMES, r_squared(k_hat, k_va.double()))),
        "modes": modes,
        "energy_held": energy,
        "hidden": hidden,
        "epochs": epochs,
        "records": {"train": len(x_tr), "val": len(x_va), "beyond_drive_range": out_tr + out_va},
        "actuator": (prov.get("actuator") or {}).get("name"),
    }


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data-dir", required=True)
    ap.add_argument("--modes", type=int, default=22)
    ap.add_argument("--hidden", type=int, default=20)
    ap.add_argument("--epochs", type=int, default=150)
    ap.add_argument("--drive-range", type=float, default=2.0, help="x the actuator's current_limit, as phm-train")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--out", default="results/fdi_capacity_probe.json")
    args = ap.parse_args(argv)
    torch.set_num_threads(args.threads)
    start = time.perf_counter()
    report = probe(args.data_dir, args.modes, args.hidden, args.epochs, args.drive_range, args.seed)
    report |= {
        "data_dir": args.data_dir,
        "seed": args.seed,
        "wall_s": round(time.perf_counter() - start, 1),
        "machine": {"cpus": torch.get_num_threads(), "platform": platform.platform()},
    }
    write_json(args.out, report)
    print(json.dumps(report, indent=2))
    return report


if __name__ == "__main__":
    main()
