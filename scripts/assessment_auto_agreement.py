"""Labels of the derived sweep (``frequencies: auto``, ``amplitude: auto``) against a hand-tuned one.

Assesses the same importance-sampled fault vectors (paper scaling) with both sweeps and writes the label
agreement, the healthy fractions, the unmeasurable-margin counts and the nominal margins as JSON:

    python scripts/assessment_auto_agreement.py --n 768 --out scripts/assessment_auto_agreement.json

``--hand`` gives the hand-tuned sweep (default: the grid and amplitude shipped before the derivation,
14 log-spaced points 12..160 Hz and 8e-5 rad, tuned for the reference actuator); ``--actuator`` another
conf/actuator/<name>.yaml.
"""

from __future__ import annotations

import argparse
import json
import time

import numpy as np
import torch
from hydra.utils import instantiate
from omegaconf import OmegaConf

from phm_torch.assessment import AssessmentFunction, SineSweep, unmeasurable_counts
from phm_torch.data.sampling import ImportanceSampler
from phm_torch.params import CONF_DIR, load_actuator

HAND_FREQUENCIES = [12.0, 14.65, 17.88, 21.82, 26.63, 32.5, 39.66, 48.41, 59.08, 72.11, 88.01, 107.41, 131.1, 160.0]
HAND_AMPLITUDE = 8.0e-5


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, default=768, help="fault vectors")
    ap.add_argument("--seed", type=int, default=7)
    ap.add_argument("--actuator", default="ema_reference")
    ap.add_argument("--out", default=None, help="JSON file (default: print only)")
    args = ap.parse_args()
    torch.set_num_threads(1)
    params = load_actuator(args.actuator)
    node = OmegaConf.load(CONF_DIR / "assessment" / "frequency_response.yaml")
    auto_sweep = instantiate(node.sweep)
    requirements = instantiate(node.requirements)
    hand_sweep = SineSweep(**{**vars(auto_sweep), "frequencies": HAND_FREQUENCIES, "amplitude": HAND_AMPLITUDE})
    k = torch.as_tensor(ImportanceSampler(params.nominal_faults, (6,), 1.0).sample(args.n, args.seed))
    out: dict = {"actuator": args.actuator, "n": args.n, "seed": args.seed}
    labels = {}
    for name, sweep in (("hand", hand_sweep), ("auto", auto_sweep)):
        af = AssessmentFunction(params, sweep, requirements)
        t0 = time.perf_counter()
        res = af(k)
        wall = time.perf_counter() - t0
        labels[name] = res.healthy.numpy()
        m = res.margins.stacked().numpy()
        out[name] = {
            "frequencies": list(af.sweep.frequencies),
            "amplitude": af.sweep.amplitude,
            "healthy_fraction": round(float(labels[name].mean()), 4),
            "unmeasurable": unmeasurable_counts(m),
            "nominal_margins": {a: round(float(v[0]), 3) for a, v in af.nominal.as_dict().items()},
            "ms_per_vector": round(1000 * wall / args.n, 2),
        }
    agree = labels["hand"] == labels["auto"]
    out["label_agreement"] = round(float(agree.mean()), 4)
    out["hand_healthy_auto_faulty"] = int((labels["hand"] & ~labels["auto"]).sum())
    out["hand_faulty_auto_healthy"] = int((~labels["hand"] & labels["auto"]).sum())
    text = json.dumps(out, indent=2)
    print(text)
    if args.out:
        with open(args.out, "w") as f:
            f.write(text + "\n")
    np.testing.assert_equal(agree.shape, (args.n,))


if __name__ == "__main__":
    main()
