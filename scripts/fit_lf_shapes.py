"""Fit the LF shape functions to the HF model; writes JSON and prints the YAML block for conf/actuator.

Usage: python scripts/fit_lf_shapes.py [--actuator ema_reference] [--out results/lf_fit.json]
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from phm_torch.lf_fit import run_fit
from phm_torch.params import load_actuator


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--actuator", default="ema_reference")
    ap.add_argument("--out", default="results/lf_fit.json")
    args = ap.parse_args()
    report = run_fit(load_actuator(args.actuator))
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(report, indent=2))
    print(json.dumps({k: report[k] for k in ("fitted", "design")}, indent=2)[:3000])
    print("lf_shape:")
    for k, v in report["fitted"].items():
        print(f"  {k}: {v:.6g}")


if __name__ == "__main__":
    main()
