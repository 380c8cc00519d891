"""A bundle's health classifier on fault vectors it never saw: the labels of another store of the same actuator.

The val split's faulty vectors number a few hundred, so a missed-fault rate of a fraction of a percent is a count of
0 to 3 there. An independent store of assessment-only labels (phm-generate with another seed: the same sampling,
other vectors) measures it on thousands:

    phm-generate actuator=ema_hvdc_rudder command=chirp_hvdc_rudder seed=7 dataset.n_train=1 dataset.n_val=1 \
        dataset.n_rul=1 dataset.n_labels=10000 data_dir=/tmp/heldout
    python scripts/classifier_heldout.py --bundle results/run/train/surrogates.pt --data-dir /tmp/heldout \
        --out heldout.json

The store must belong to the bundle's actuator and command (checked), and must not be the one it was trained on
(its fingerprint is compared). Writes {n, faulty, accuracy, missed, missed_fault_rate, false_alarms,
false_alarm_rate, split, store, bundle} as JSON.

``--uncertain N``: the classifier's errors and N of its right answers (at random) are assessed again with the
store's own assessment config, and the report says how many of each have an uncertain label (the window before the
last reads another label: a reading that has not settled or is not periodic decides it; docs/dataset.md, "Settling
and refinement") and how many labels the re-assessment reproduces (``uncertain`` in the JSON).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import torch

from phm_torch.data.store import DatasetStore, read_labelled, recorded_assessment
from phm_torch.io.atomic import write_json
from phm_torch.surrogates.bundle import SurrogateBundle
from phm_torch.surrogates.metrics import confusion


def heldout_confusion(bundle: SurrogateBundle, data_dir: str, split: str = "labels") -> dict[str, float | int]:
    """Counts and rates of ``bundle.is_healthy`` against the phi_a labels of ``split`` of the store ``data_dir``."""
    with DatasetStore(data_dir) as store:
        bundle.check_store(store.provenance, f"store {data_dir}")
        trained_on = bundle.extra.get("data_fingerprint")
        if trained_on is not None and trained_on == store.manifest.get("fingerprint"):
            raise ValueError(f"store {data_dir} is the one the bundle was trained on: give an independent one")
    k, healthy = read_labelled(data_dir, (split,), ())
    k_t, h = torch.as_tensor(k, dtype=torch.float64), torch.as_tensor(healthy).bool()
    counts = confusion(bundle.is_healthy(k_t), h)
    return {
        "n": int(h.numel()),
        "faulty": counts["n_faulty"],
        "accuracy": counts["accuracy"],
        "missed": counts["missed_faults"],
        "missed_fault_rate": counts["missed_fault_rate"],
        "false_alarms": counts["false_alarms"],
        "false_alarm_rate": counts["false_alarm_rate"],
    }


def uncertain_labels(
    bundle: SurrogateBundle, data_dir: str, split: str, n_right: int, seed: int = 0
) -> dict[str, dict[str, int]]:
    """The classifier's errors on ``split`` of ``data_dir`` (missed faults, false alarms) and ``n_right`` of its right
    answers assessed again with the store's recorded assessment: per group, how many there are, how many labels
    the re-assessment reproduces and how many are uncertain (:class:`~phm_torch.assessment.health.Assessment`)."""
    with DatasetStore(data_dir) as store:
        metadata = store.metadata
    try:
        assessment, _ = recorded_assessment(metadata)
    except ValueError as e:
        raise ValueError(f"store {data_dir}: {e}") from None
    k, healthy = read_labelled(data_dir, (split,), ())
    k_t, h = torch.as_tensor(k, dtype=torch.float64), torch.as_tensor(healthy).bool()
    said = bundle.is_healthy(k_t).bool()
    right = torch.nonzero(said == h)[:, 0].numpy()
    rng = np.random.default_rng(seed)
    groups = {
        "missed_faults": torch.nonzero(said & ~h)[:, 0].numpy(),
        "false_alarms": torch.nonzero(~said & h)[:, 0].numpy(),
        "right": rng.choice(right, size=min(n_right, len(right)), replace=False),
    }
    out = {}
    for name, rows in groups.items():
        if len(rows) == 0:
            out[name] = {"n": 0, "reproduced": 0, "uncertain": 0}
            continue
        res = assessment(k_t[rows])
        out[name] = {
            "n": len(rows),
            "reproduced": int((res.healthy == h[rows]).sum()),
            "uncertain": int(res.uncertain.sum()),
        }
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--bundle", required=True, help="SurrogateBundle (phm-train's surrogates.pt)")
    ap.add_argument("--data-dir", required=True, help="an independent store of the same actuator and command")
    ap.add_argument("--split", default="labels", help="the split whose labels judge the classifier")
    ap.add_argument("--out", default=None, help="JSON report (default: print only)")
    ap.add_argument("--uncertain", type=int, default=0, metavar="N", help="assess the errors and N right answers again")
    args = ap.parse_args()
    if args.uncertain < 0:
        raise SystemExit(f"classifier_heldout: error: --uncertain must be >= 0, got {args.uncertain}")
    try:
        bundle = SurrogateBundle.load(args.bundle)
        counts = heldout_confusion(bundle, args.data_dir, args.split)
        if args.uncertain:
            counts["uncertain"] = uncertain_labels(bundle, args.data_dir, args.split, args.uncertain)
    except ValueError as e:  # another actuator's store, the training store, a missing split: one line
        raise SystemExit(f"classifier_heldout: error: {e}") from None
    report = {
        **counts,
        "split": args.split,
        "store": args.data_dir,
        "bundle": args.bundle,
    }
    if args.out:
        write_json(Path(args.out), report)
    print(json.dumps(report, indent=2))


if __name__ == "__main__":
    main()
