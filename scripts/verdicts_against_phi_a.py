"""Verdicts of one or more exported pipelines of an actuator against the assessment function phi_a itself, on the
same clean records: the corruption suite's 1,000 clean records (125 paper-scaled fault vectors at 0-3 % noise,
with their command and position columns, on phm-predict's path). Pipelines trained on differently sampled stores
cannot be compared on their own val splits; on these records they can (docs/results.md, the second actuator).

    python scripts/verdicts_against_phi_a.py --store /tmp/rud/run/data --pipeline old.pt --pipeline new.pt \
        [--out verdicts.json]

Per pipeline: the flagged share, and among the unflagged records the missed faults (phi_a faulty, said healthy),
the false alarms, and the wrong verdicts near nominal (every damage below 0.2). phi_a is built from the store's
recorded assessment config; the HF records come from the corruption suite's cache.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import torch

from phm_torch.checks import build
from phm_torch.data.store import DatasetStore
from phm_torch.io.atomic import atomic_open
from phm_torch.online.corruption_suite import CACHE, clean_records, contract_of, pipeline_conditions
from phm_torch.online.diagnosis import diagnose

NEAR = 0.2  # "near nominal": every damage component within this of nominal


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--store", type=Path, required=True, help="the store whose assessment config labels phi_a")
    ap.add_argument("--pipeline", type=Path, action="append", required=True, help="an exported pipeline (repeat)")
    ap.add_argument("--cache", type=Path, default=CACHE)
    ap.add_argument("--clean", type=int, default=125, help="fault vectors of the clean records (x 8 records)")
    ap.add_argument("--out", type=Path, default=None)
    args = ap.parse_args(argv)
    torch.set_num_threads(1)
    with DatasetStore(args.store) as store:
        config = (store.metadata.get("config") or {}).get("assessment")
    if config is None:
        raise SystemExit(f"verdicts_against_phi_a: error: store {args.store} records no assessment config")
    first = torch.jit.load(str(args.pipeline[0]))
    params, _, _ = pipeline_conditions(args.pipeline[0])
    cases = clean_records(first, args.pipeline[0], args.clean, args.cache)
    k = torch.stack([c.k for c in cases]).double()
    healthy = build(config, "assessment", params=params)(k).healthy.bool()
    deviation = (k - torch.tensor(params.nominal_faults, dtype=torch.float64)).abs()
    deviation[:, 6] = 0.0  # the eccentricity phase is no damage
    near = deviation.amax(1) < NEAR
    report: dict = {"store": str(args.store), "records": len(cases), "phi_a_healthy": float(healthy.double().mean())}
    for path in args.pipeline:
        model = torch.jit.load(str(path))
        contract = contract_of(model, path)
        out = [diagnose(model, c.record, contract) for c in cases]
        flagged = torch.tensor([o["out_of_distribution"] for o in out])
        said = torch.tensor([bool(o["healthy"]) for o in out])
        kept = ~flagged
        faulty, fine = kept & ~healthy, kept & healthy
        report[str(path)] = {
            "flagged": float(flagged.double().mean()),
            "missed_faults": int((faulty & said).sum()) / max(1, int(faulty.sum())),
            "false_alarms": int((fine & ~said).sum()) / max(1, int(fine.sum())),
            "near_nominal_wrong": int((kept & near & (said != healthy)).sum()) / max(1, int((kept & near).sum())),
            "near_nominal_records": int((kept & near).sum()),
        }
    if args.out is not None:
        with atomic_open(args.out, "w") as fh:
            json.dump(report, fh, indent=1)
    print(json.dumps(report, indent=1))
    return report


if __name__ == "__main__":
    main()
