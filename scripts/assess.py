"""The health label phi_a gives fault vectors: the truth to judge phm-predict's verdicts against.

Usage:
    python scripts/assess.py --actuator ema_reference --faults 0.5,0,0,0,0,0,0.5,0.5 0,0.15,0,0,0,0,0.5,0.7
    python scripts/assess.py --actuator $MY_CONF/actuator/my_ema.yaml --csv vectors.csv [--rotor-positions 1]

Each vector is k1..k8 (comma-separated, in [0, 1]); ``--csv`` reads a file with a header and the columns k1..k8 (or
the fault names of phm_torch.faults). The assessment config is the shipped one unless ``--assessment`` names
another (it must be the one your data were labelled with for the label to be the pipeline's truth). Prints one JSON
line per vector: the vector, ``healthy``, ``uncertain`` (the window before the last reads otherwise) and the margins
[Hz, deg, dB]. Uncompiled, one thread: ~20 ms a vector in a batch at the reference's sweep and one rotor position; the shipped
three read a vector at the next position only while it passes (up to 3x; the margins of a vector that failed early
are the worst of the positions read).
"""

from __future__ import annotations

import argparse
import csv
import json
import sys

import torch

from phm_torch.assessment import AssessmentFunction
from phm_torch.assessment.label_check import load_assessment
from phm_torch.faults import FAULT_NAMES, N_FAULTS, as_fault_tensor
from phm_torch.params import load_actuator


def parse_vector(text: str) -> list[float]:
    """k1..k8 from ``"a,b,..."``; a ValueError naming the value otherwise."""
    try:
        values = [float(v) for v in text.split(",")]
    except ValueError:
        raise ValueError(f"--faults: {text!r} is not {N_FAULTS} comma-separated numbers") from None
    if len(values) != N_FAULTS:
        raise ValueError(f"--faults: {text!r} has {len(values)} values, not {N_FAULTS} (k1..k8)")
    return values


def read_csv(path: str) -> list[list[float]]:
    """Vectors from a CSV whose header names k1..k8 or the fault names."""
    with open(path, newline="") as fh:
        rows = list(csv.DictReader(fh))
    if not rows:
        raise ValueError(f"--csv: {path!r} has no rows")
    for names in ([f"k{i + 1}" for i in range(N_FAULTS)], list(FAULT_NAMES)):
        if set(names) <= set(rows[0]):
            return [[float(r[n]) for n in names] for r in rows]
    raise ValueError(f"--csv: {path!r} needs the columns k1..k8 or {list(FAULT_NAMES)}; it has {list(rows[0])}")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--actuator", default="ema_reference", help="conf/actuator/<name>.yaml name, or a YAML path")
    ap.add_argument("--faults", nargs="*", default=[], help="fault vectors k1..k8, comma-separated")
    ap.add_argument("--csv", help="a CSV of fault vectors (columns k1..k8 or the fault names)")
    ap.add_argument("--assessment", help="assessment config YAML (default the shipped conf/assessment)")
    ap.add_argument("--rotor-positions", type=int, help="the sweep's rotor_positions (default: the config's)")
    args = ap.parse_args(argv)
    vectors = [parse_vector(v) for v in args.faults] + (read_csv(args.csv) if args.csv else [])
    if not vectors:
        ap.error("give --faults or --csv")
    torch.set_num_threads(1)
    k = as_fault_tensor(torch.tensor(vectors, dtype=torch.float64), torch.float64, "cpu")
    sweep, requirements = load_assessment(args.assessment, args.rotor_positions)
    phi = AssessmentFunction(load_actuator(args.actuator), sweep, requirements)
    found = phi(k)
    for i, vector in enumerate(vectors):
        margins = {name: round(float(v[i]), 3) for name, v in found.margins.as_dict().items()}
        row = {"k": vector, "healthy": bool(found.healthy[i]), "uncertain": bool(found.uncertain[i]), **margins}
        print(json.dumps(row))
    return 0


if __name__ == "__main__":
    sys.exit(main())
