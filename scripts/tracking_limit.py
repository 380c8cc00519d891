"""What a life split leaves to know (issue 25's targets): the tracker fed the true damage, beside phm-track's run.

    python scripts/tracking_limit.py --life DIR [--life DIR ...] [--track-out DIR ...] \
        [--error-std 1e-4 2e-3] [--pipeline pretrained/online_surrogates_best.pt] [--out X.json]

``--life``: a life split's folder (its ``truth.json``, phm-generate's ``life`` split). ``--track-out``: phm-track's
``out_dir`` of the same split (its ``metrics.json``), one per ``--life`` in the same order, put side by side.
For each split and measurement error (``phm_torch.tracking.information_limit``): the tracker's figures with the
true k measured to ``error_std`` (the FDI removed from the chain) and the health classifier's own end-of-life
flags on the true k. With ``--track-out`` the filter is that run's (its pipeline and tracker settings, from its
``track.json``); without, the pipeline is ``--pipeline`` with phm-track's default settings (``--verdict`` and
``--faulty-at`` change the rule).
``--per-component`` (needs ``--track-out``): also, for each component in turn, the true k with that component read
as the phm-track run fused it (the others at the smallest ``--error-std``): which measurement costs the horizon.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
from pathlib import Path

import torch
import yaml

from phm_torch.faults import FAULT_NAMES
from phm_torch.io.atomic import write_json
from phm_torch.online.export import read_metadata
from phm_torch.params import CONF_DIR
from phm_torch.tracking import TrackerSettings, build_tracker
from phm_torch.tracking.information_limit import fused_readings, information_limit, track_truth

ROOT = Path(__file__).resolve().parents[1]
FIGURES = (
    "coverage_5_95",
    "alpha_lambda",
    "prognostic_horizon",
    "eol_flagged_within_one_inspection",
    "median_relative_band_width_second_half",
)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--life", nargs="+", required=True, help="life split folders (each with truth.json)")
    ap.add_argument("--track-out", nargs="*", default=[], help="phm-track out_dir of each split, same order")
    ap.add_argument("--error-std", nargs="+", type=float, default=[1e-4], help="measurement errors [k units]")
    ap.add_argument("--pipeline", default=str(ROOT / "pretrained" / "online_surrogates_best.pt"))
    ap.add_argument("--verdict", choices=["record", "posterior"], default=TrackerSettings().verdict)
    ap.add_argument("--faulty-at", choices=["p50", "p5"], default=TrackerSettings().faulty_at)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--per-component", action="store_true", help="each component read as the run fused it")
    ap.add_argument("--out", default=str(ROOT / "docs" / "tracking_limit.json"))
    args = ap.parse_args()
    if args.track_out and len(args.track_out) != len(args.life):
        ap.error(f"--track-out: {len(args.track_out)} folders for {len(args.life)} --life folders")
    if args.per_component and not args.track_out:
        ap.error("--per-component needs --track-out (the run whose readings are put back)")
    for folder in args.track_out:
        for name in ("metrics.json", "track.json"):
            if not (Path(folder) / name).is_file():
                ap.error(f"--track-out {folder!r}: no {name} there (run phm-track with truth= first)")
    torch.set_num_threads(1)
    damage = yaml.safe_load((CONF_DIR / "damage" / "coupled.yaml").read_text())  # phm-track's fallback
    out: dict = {"splits": {}}
    for j, life in enumerate(args.life):
        run = json.loads((Path(args.track_out[j]) / "track.json").read_text()) if args.track_out else None
        pipeline = run["pipeline"] if run else args.pipeline
        model, metadata = torch.jit.load(pipeline), read_metadata(pipeline)
        if run:  # the run's own filter
            fields = {f.name for f in dataclasses.fields(TrackerSettings)}
            settings = TrackerSettings(**{k: v for k, v in run["tracker"]["settings"].items() if k in fields})
        else:
            settings = TrackerSettings(verdict=args.verdict, faulty_at=args.faulty_at)
        truth_path = Path(life) / "truth.json"
        if not truth_path.is_file():
            truth_path = Path(life) / "life" / "truth.json"
        if not truth_path.is_file():
            ap.error(f"--life {life!r}: no truth.json there (nor in its life/ folder)")
        truth = json.loads(truth_path.read_text())
        split: dict = {"truth": str(truth_path), "pipeline": pipeline, "settings": vars(settings), "limits": []}
        for error_std in args.error_std:
            tracker, _ = build_tracker(model, metadata, damage, settings, pipeline)
            found = information_limit(track_truth(tracker, truth, error_std, args.seed), truth)
            split["limits"].append(found)
            row = {k: found["tracking"][k] for k in FIGURES}
            print(f"{life} true k +- {error_std:g}: {row}; classifier on the true k: {found['classifier_on_true_k']}")
        if args.track_out:
            metrics = json.loads((Path(args.track_out[j]) / "metrics.json").read_text())
            split["phm_track"] = {k: metrics["tracker"][k] for k in FIGURES}
            split["phm_track_out_dir"] = args.track_out[j]
            print(f"{life} phm-track: {split['phm_track']}")
        if args.per_component:
            readings = fused_readings(run)
            split["per_component"] = {}
            for c, name in enumerate(FAULT_NAMES):
                tracker, _ = build_tracker(model, metadata, damage, settings, pipeline)
                found = information_limit(
                    track_truth(tracker, truth, min(args.error_std), args.seed, readings, (c,)), truth
                )
                split["per_component"][name] = {k: found["tracking"][k] for k in FIGURES}
                print(f"{life} {name} as read: {split['per_component'][name]}")
        out["splits"][life] = split
    write_json(args.out, out)
    print("wrote", args.out)


if __name__ == "__main__":
    main()
