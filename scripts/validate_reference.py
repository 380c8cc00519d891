"""Compare the HF (and LF) simulator with the reference figures of ema_reference.md §6; writes JSON.

Usage: python scripts/validate_reference.py [--out results/validation.json] [--fidelity hf]
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import torch

from phm_torch.command import Chirp
from phm_torch.metrics import chirp_last_cycle, nrmse
from phm_torch.params import load_actuator
from phm_torch.simulator import EMASimulator

# ema_reference.md §6 (independent implementation): fault -> (current NRMSE, position NRMSE), fractions.
REFERENCE_NRMSE = {
    "k1": (0.108, 0.0024),
    "k2": (0.230, 0.0235),
    "k3": (0.197, 0.0036),
    "k4": (0.305, 0.0060),
    "k5": (0.298, 0.0060),
    "k6": (0.069, 0.0012),
    "k7": (0.107, 0.0022),
    "k8=1": (0.064, 0.038),
    "k8=0": (0.127, 0.090),
}
REFERENCE_NOMINAL = {
    "tracking_rms_mrad": 1.14,
    "tracking_max_mrad": 2.59,
    "amplitude_ratio": 0.93,
    "lag_deg": 30.0,
    "peak_current_A": 2.30,
    "peak_speed_rad_s": 80.0,
}


def fault_cases(nominal: list[float]) -> dict[str, list[float]]:
    cases = {"nominal": list(nominal)}
    for i in range(6):
        k = list(nominal)
        k[i] = 1.0
        cases[f"k{i + 1}"] = k
    cases["k6=1"] = cases["k6"]
    k = list(nominal)
    k[5], k[6] = 1.0, 0.0  # k7 varied against k6 = 1, k7 = 0.5
    cases["k7"] = k
    for v in (1.0, 0.0):
        k = list(nominal)
        k[7] = v
        cases[f"k8={v:g}"] = k
    del cases["k6=1"]
    return cases


def validate(fidelity: str = "hf", compile: bool = False) -> dict:
    p = load_actuator()
    cmd = Chirp()
    cases = fault_cases(list(p.nominal_faults))
    sim = EMASimulator(p, fidelity, compile=compile)
    t0 = time.perf_counter()
    s = sim.run(torch.tensor(list(cases.values()), dtype=torch.float64), cmd, cmd.duration)
    elapsed = time.perf_counter() - t0
    names = list(cases)
    cur, pos = s["current"], s["position"]
    i0 = names.index("nominal")
    err = pos[i0] - s["command"][i0]
    ratio, lag = chirp_last_cycle(s.time, s["command"][i0], pos[i0], cmd.f_end, cmd.duration)
    nominal = {
        "tracking_rms_mrad": err.pow(2).mean().sqrt().item() * 1e3,
        "tracking_max_mrad": err.abs().max().item() * 1e3,
        "amplitude_ratio": ratio,
        "lag_deg": lag,
        "peak_current_A": cur[i0].max().item(),
        "peak_speed_rad_s": s["speed"][i0].abs().max().item(),
    }
    faults = {}
    for name, ref in REFERENCE_NRMSE.items():
        j = names.index(name)
        base = names.index("k6") if name == "k7" else i0
        faults[name] = {
            "current": nrmse(cur[j], cur[base]).item(),
            "position": nrmse(pos[j], pos[base]).item(),
            "reference_current": ref[0],
            "reference_position": ref[1],
        }
    return {
        "fidelity": fidelity,
        "elapsed_s": elapsed,
        "nominal": nominal,
        "reference_nominal": REFERENCE_NOMINAL,
        "faults": faults,
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--fidelity", default="hf", choices=["hf", "lf"])
    ap.add_argument("--out", default="results/validation_{fidelity}.json")
    ap.add_argument("--compile", action="store_true")
    args = ap.parse_args()
    res = validate(args.fidelity, args.compile)
    out = Path(args.out.format(fidelity=args.fidelity))
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(res, indent=2))
    print(json.dumps(res, indent=2))


if __name__ == "__main__":
    main()
