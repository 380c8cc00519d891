"""How far an actuator's reference RUL moves when its health boundary moves by an actuator-independent amount.

The RUL "from the true k" differs from the reference only where the pipeline's health classifier puts the boundary
elsewhere than the assessment function: its relative error is the classifier's boundary error times how strongly the
actuator's RUL depends on where the boundary lies. An actuator whose nominal margin sits close to its requirement (a
slim gain margin) turns the same boundary error into a larger RUL error. This script measures that dependence on a
``phm-run`` output: the reference RULs of the run's ``rul`` split computed again with every requirement's margin
excess shifted by ``--eps`` (0.01: each requirement 1 % stricter), against the reference the evaluate stage cached
in the store (``data/rul_reference_rul.json``).

    python scripts/rul_boundary_sensitivity.py --run /tmp/paper_run --eps 0.01 --out sensitivity.json

Writes {run, actuator, eps, usable, median_abs_rel_change, median_rel_change, wall_s} as JSON (a few minutes: one
reference propagation of the split, LF assessments along every trajectory).
"""

from __future__ import annotations

import argparse
import json
import time
from collections.abc import Callable
from pathlib import Path

import torch

from phm_torch import provenance
from phm_torch.apps.evaluate import settings_from_config
from phm_torch.apps.run import compose_stage
from phm_torch.checks import build
from phm_torch.io.atomic import write_json
from phm_torch.pipelines.evaluate.inputs import read_inputs
from phm_torch.prognostics.damage import DamageModel
from phm_torch.prognostics.reference import margin_score, reference_rul


def boundary_sensitivity(
    damage: DamageModel,
    score: Callable[[torch.Tensor], torch.Tensor],
    k: torch.Tensor,
    deltas: torch.Tensor,
    base: torch.Tensor,
    eps: float,
    step_hours: float,
    refine_iterations: int,
) -> dict[str, float | int]:
    """The reference RULs of ``k`` (B, 8) stopped by ``score - eps`` against ``base`` (B, 3) [h], the RULs stopped
    by ``score``: {usable (vectors with a positive base RUL), median_abs_rel_change, median_rel_change}."""
    if not 0 < eps < 0.5:
        raise ValueError(f"eps must be in (0, 0.5), got {eps}")
    stricter = reference_rul(damage, lambda x: score(x) - eps, k, deltas, step_hours, refine_iterations)
    usable = base[:, 1] > 0
    change = (stricter[usable, 1] - base[usable, 1]) / base[usable, 1]
    return {
        "usable": int(usable.sum()),
        "median_abs_rel_change": float(change.abs().median()),
        "median_rel_change": float(change.median()),
    }


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--run", type=Path, required=True, help="a phm-run out_dir (data/, train/, evaluate/)")
    ap.add_argument("--eps", type=float, default=0.01, help="shift of the relative margin excess (0.01 = 1 %%)")
    ap.add_argument("--out", type=Path, default=None, help="JSON written (atomically); default: print only")
    args = ap.parse_args(argv)
    cache = args.run / "data" / "rul_reference_rul.json"
    if not cache.is_file():
        raise SystemExit(f"{cache}: no cached reference RUL (run the evaluate stage on this store first)")
    overrides = [f"data_dir={args.run / 'data'}", f"bundle={args.run / 'train' / 'surrogates.pt'}", "out_dir=."]
    settings = settings_from_config(compose_stage("evaluate", overrides))
    inputs = read_inputs(settings)
    calibration = json.loads((args.run / "evaluate" / "rul_calibration.json").read_text())
    t0 = time.perf_counter()
    figures = boundary_sensitivity(
        inputs.damage,
        margin_score(build(inputs.assessment, "assessment", params=inputs.params)),
        inputs.k,
        torch.tensor(calibration["deltas"], dtype=torch.float64),
        torch.tensor(json.loads(cache.read_text())["rul"], dtype=torch.float64),
        args.eps,
        settings.reference.step_hours,
        settings.reference.refine_iterations,
    )
    result = {
        "run": str(args.run),
        "actuator": provenance.describe(inputs.prov["actuator"]),
        "eps": args.eps,
        **figures,
        "wall_s": round(time.perf_counter() - t0, 1),
    }
    print(json.dumps(result, indent=2))
    if args.out:
        write_json(args.out, result)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
