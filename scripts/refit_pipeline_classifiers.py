"""Give an exported TorchScript pipeline the classifiers of the assessment function its actuator ships now.

A pipeline's health classifier learns phi_a's labels, and its verdict classifier learns them from the FDI's estimates.
When phi_a changes (the sweep derived from the actuator replaced the hand-tuned one), the shipped pipeline keeps the
old boundary. Its FDI is unaffected, but every verdict and RUL event is judged by a boundary the new labels do not
share. This script keeps the FDI and everything calibrated on it, and changes three things:
- the health classifier is taken from a bundle trained on a store labelled by the current phi_a
  (``phm-train``'s, boundary refinement included), or, with ``--fit-classifier``, fitted here on that store's
  training and labels splits exactly as phm-train fits it (its composed config: the classifier kind, the boundary
  refinement on importance-sampled and damage-law path candidates; phi_a is all it needs, no FDI training), or,
  with ``--keep-classifier``, kept;
- with ``--refit-verdict``, the verdict classifier is refit on the pipeline's own estimates of that store's training
  records (1 % current noise), with their labels, as phm-train fits it (on 10,000 records instead of the pipeline's
  own 80,000 it lost more near nominal than it gained; on 40,000 it gained everywhere: pretrained/README.md), and
  ``--verdict-life`` adds the (noisy) records of a life split with their phi_a labels;
- the two calibrations that read the classifiers are redone on the store's val split, as phm-evaluate does them:
  the FDI band of the full-flow RUL, and P(faulty)'s Platt scaling.
The classifiers are cast to the pipeline's dtype (``--keep-classifier`` alone does only that and the two
calibrations). With ``--rul-band`` the physics RUL band, whose event is the health classifier, is calibrated again
first, as phm-evaluate calibrates it (the composed evaluate config's damage law and ``rul`` settings, on the store's
``rul`` split), and that damage law goes into the metadata (for a pipeline whose band predates the law's wear-rate
scale; the shipped one keeps its band: measured, pretrained/README.md). The file's metadata is kept otherwise.

    python scripts/refit_pipeline_classifiers.py --pipeline tests/data/pretrained_v0.pt --data-dir data/paper \
        --bundle results/train/surrogates.pt --out /tmp/p/online.pt
    python scripts/refit_pipeline_classifiers.py --pipeline pretrained/online_surrogates_best.pt \
        --data-dir data/paper --fit-classifier --work-dir /tmp/p/fit --out /tmp/p/online.pt
    python scripts/refit_pipeline_classifiers.py --pipeline pretrained/online_surrogates_best.pt \
        --data-dir data/paper40k --keep-classifier --refit-verdict --out /tmp/p/online.pt
    python scripts/refit_pipeline_classifiers.py --pipeline pretrained/online_surrogates_best.pt \
        --data-dir data/paper --keep-classifier --rul-band --out /tmp/p/online.pt
    phm-export pipeline=/tmp/p/online.pt format=[torchscript,export] out=/tmp/p2/online_surrogates_best.pt
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any

import numpy as np
import torch
from hydra.utils import instantiate

from phm_torch import provenance
from phm_torch.apps.common import plain
from phm_torch.apps.run import compose_stage
from phm_torch.apps.train import settings_from_config
from phm_torch.checks import build
from phm_torch.data import DatasetStore
from phm_torch.data.store import recorded_actuator
from phm_torch.io.measurement_csv import read_measurement
from phm_torch.online.export import export_torchscript
from phm_torch.online.from_torchscript import pipeline_from_torchscript
from phm_torch.pipelines.evaluate.calibration import fdi_band, noisy, verdict_scaling
from phm_torch.pipelines.train import fit_health_classifier, store_labeller
from phm_torch.prognostics.rul import DeterministicRUL, RULEstimator
from phm_torch.surrogates import SurrogateBundle
from phm_torch.surrogates.classifiers import MLPClassifier

NOISE = (
    0.01  # relative current noise of the verdict classifier's training records and the band's (as phm-train/-evaluate)
)
BATCH = 1024


def _split(store: DatasetStore, name: str) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    view = store.split(name)
    k = torch.as_tensor(np.asarray(view.K), dtype=torch.float64)
    return (
        k,
        torch.as_tensor(np.asarray(view.current), dtype=torch.float64),
        torch.as_tensor(np.asarray(view.healthy)).bool(),
    )


def _rates(score: torch.Tensor, healthy: torch.Tensor) -> dict[str, float]:
    said = score > 0
    return {
        "accuracy": float((said == healthy).double().mean()),
        "missed_fault_rate": float((said & ~healthy).double().sum() / max(1, int((~healthy).sum()))),
    }


def _life_records(life_dir: Path, n_full: int) -> tuple[torch.Tensor, torch.Tensor]:
    """The current (N, n_full) [A] of every inspection record of a life split and its phi_a label (N,) bool."""
    truth = json.loads((life_dir / "truth.json").read_text())
    currents, healthy = [], []
    for history in truth["actuators"].values():
        for inspection in history["inspections"]:
            m = read_measurement(life_dir / inspection["file"], optional=("command", "position"))
            if len(m.current) != n_full:
                raise ValueError(f"{life_dir / inspection['file']}: {len(m.current)} samples, the pipeline's {n_full}")
            currents.append(torch.as_tensor(m.current, dtype=torch.float64))
            healthy.append(bool(inspection["healthy"]))
    return torch.stack(currents), torch.tensor(healthy)


def _fit_classifier(args: argparse.Namespace, k: torch.Tensor, healthy: torch.Tensor) -> tuple[Any, dict[str, Any]]:
    """The health classifier phm-train would fit on the store ``args.data_dir`` (its composed train config)."""
    work = Path(args.work_dir or Path(args.out).with_suffix(".fit"))
    cfg = compose_stage("train", [f"data_dir={args.data_dir}", f"out_dir={work}", *args.train_override])
    settings = settings_from_config(cfg)
    classifier = instantiate(cfg.classifier, _convert_="all")
    with DatasetStore(args.data_dir) as store:
        labeller = store_labeller(settings, store.metadata)
        fingerprint = store.manifest.get("fingerprint")
    timing: dict[str, float] = {}
    n, info = fit_health_classifier(settings, classifier, k, healthy, labeller, fingerprint, timing)
    return classifier, {"vectors": n, "refinement": info, "timing_s": timing}


def physics_band(
    pipe: Any, damage_cfg: dict[str, Any], nominal: list[float], rul: Any, k: torch.Tensor, seed: int
) -> dict[str, Any]:
    """Calibrate ``pipe``'s physics RUL band (deltas, direction, rate scales) on the fault vectors ``k`` (B, 8) as
    phm-evaluate does: the damage law ``damage_cfg`` (a ``conf/damage`` node, built with the actuator's ``nominal``
    vector) and the ``rul`` settings (``n_samples``, ``refine_iterations``, ``band``, ``delta_bracket``), the
    pipeline's own health classifier as the event. Returns a report: the band before and after, and how often each
    holds the law's own Monte Carlo RULs (eps and the wear-rate scale drawn) from the true k."""
    damage = build(dict(damage_cfg), "damage", nominal=nominal)
    a, _ = damage.transitions(damage.grid)
    if a.shape != pipe.propagators.shape or not torch.allclose(a.to(pipe.propagators), pipe.propagators, rtol=1e-5):
        raise ValueError("--rul-band: the composed damage law's propagators are not the pipeline's (another law)")
    weights = pipe.times.dtype

    def score(x: torch.Tensor) -> torch.Tensor:
        return (pipe.classifier(x.to(weights)) - pipe.classifier.threshold).to(torch.float64)

    est = RULEstimator(damage, score, int(rul["n_samples"]), int(rul["refine_iterations"]))
    det = DeterministicRUL(est, str(rul["band"]))
    det.calibrate(k, torch.Generator().manual_seed(seed), bracket=float(rul["delta_bracket"]))
    runs = est.estimate(k, torch.Generator().manual_seed(seed + 1)).samples  # (B, n) RULs of possible actuators

    def holds() -> float:  # share of the Monte Carlo RULs inside the pipeline's true-k band
        with torch.no_grad():
            band = pipe.rul(k.to(weights)).to(torch.float64)
        inside = (runs >= band[:, :1]) & (runs <= band[:, 2:])
        return float(inside.double().mean())

    before = {"rate_scales": pipe.rate_scales.tolist(), "deltas": pipe.deltas.tolist(), "holds_monte_carlo": holds()}
    deltas, scales = det.pipeline_parameters()
    pipe.deltas.copy_(deltas.to(pipe.deltas))
    pipe.direction.copy_(det.direction.to(pipe.direction))
    pipe.rate_scales.copy_(scales.to(pipe.rate_scales))
    after = {"rate_scales": pipe.rate_scales.tolist(), "deltas": pipe.deltas.tolist(), "holds_monte_carlo": holds()}
    return {"band": det.variant, "vectors": int(k.shape[0]), "before": before, "after": after}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--pipeline", required=True, help="the TorchScript pipeline file to refit")
    ap.add_argument("--data-dir", required=True, help="a store of the pipeline's actuator and command, current phi_a")
    source = ap.add_mutually_exclusive_group(required=True)
    source.add_argument("--bundle", help="a phm-train bundle on that store: its health classifier is taken")
    source.add_argument(
        "--fit-classifier",
        action="store_true",
        help="fit the health classifier on the store as phm-train does (its train config, refinement included)",
    )
    source.add_argument(
        "--keep-classifier", action="store_true", help="keep the pipeline's health classifier (with --refit-verdict)"
    )
    ap.add_argument("--work-dir", default=None, help="with --fit-classifier: the refinement's label cache (resumable)")
    ap.add_argument("--train-override", action="append", default=[], help="with --fit-classifier: a phm-train override")
    ap.add_argument("--out", required=True)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument(
        "--verdict-life",
        action="append",
        default=[],
        help="with --refit-verdict: a life split (phm-generate stage=life) whose records join its training set",
    )
    ap.add_argument(
        "--refit-verdict",
        action="store_true",
        help="also refit the verdict classifier on the store's training records (fewer than the pipeline's own)",
    )
    ap.add_argument(
        "--rul-band",
        action="store_true",
        help="also calibrate the physics RUL band again (under the composed damage law, on the rul split)",
    )
    args = ap.parse_args()
    torch.set_num_threads(1)
    pipe, metadata = pipeline_from_torchscript(args.pipeline)
    with DatasetStore(args.data_dir) as store:
        recorded = store.provenance or {}
        assessment = (store.metadata.get("config") or {}).get("assessment")  # the phi_a of the store's labels
        # the store and the bundle must be of the pipeline's actuator and command
        provenance.require_same(recorded, metadata.get("provenance") or {}, f"store {args.data_dir}")
        train_k, train_x, train_h = _split(store, "train")
        val_k, val_x, val_h = _split(store, "val")
        rul_k, nominal = None, None
        if args.rul_band:  # the band's vectors, and the actuator's nominal vector its damage law is built with
            rul_k = torch.as_tensor(np.asarray(store.split("rul").K), dtype=torch.float64)
            nominal = list(recorded_actuator(store.metadata).nominal_faults)
    dtype = pipe.times.dtype
    before = {}
    with torch.no_grad():
        before["verdict_val"] = _rates(pipe(val_x.to(dtype))[1], val_h)
        before["health_val"] = _rates(pipe.classifier(val_k.to(dtype)) - pipe.classifier.threshold, val_h)
        if args.refit_verdict:
            noisy_train = noisy(train_x, NOISE, args.seed).to(dtype)
            k_hat = torch.cat([pipe(noisy_train[i : i + BATCH])[0] for i in range(0, len(noisy_train), BATCH)])
            del noisy_train
            for life in args.verdict_life:  # records along damage paths, noisy as written, labelled by phi_a
                life_x, life_h = _life_records(Path(life), int(pipe.n_full))
                k_life = torch.cat([pipe(life_x[i : i + BATCH].to(dtype))[0] for i in range(0, len(life_x), BATCH)])
                k_hat, train_h = torch.cat([k_hat, k_life]), torch.cat([train_h, life_h])
                before[f"verdict_life_records_{Path(life).name}"] = len(life_h)
    # the classifiers in the pipeline's dtype: a float64 classifier (the refits' before 2026-11-26, evening) cost a
    # third of a batched step's throughput, the RUL search scoring ~12 rows per propagation
    weights = pipe.times.dtype
    if args.keep_classifier:
        health, fit_report = pipe.classifier, None
    elif args.fit_classifier:
        health, fit_report = _fit_classifier(args, train_k, train_h)
    else:
        bundle = SurrogateBundle.load(args.bundle)
        provenance.require_same(bundle.provenance, recorded, f"bundle {args.bundle}")
        health, fit_report = bundle.classifier, None
    pipe.classifier = health.to(weights)
    if args.refit_verdict:
        pipe.verdict_classifier = MLPClassifier(seed=args.seed).fit(k_hat.double(), train_h).to(weights)
    else:
        pipe.verdict_classifier = pipe.verdict_classifier.to(weights)
    damage_meta, physics = {}, None
    if rul_k is not None:  # as phm-evaluate: its composed damage law and rul settings, the store actuator's nominal
        evaluate = compose_stage("evaluate", [f"data_dir={args.data_dir}"])
        damage_meta = plain(evaluate.damage)
        physics = physics_band(pipe, damage_meta, nominal, plain(evaluate.rul), rul_k, args.seed)
    band_signals = noisy(val_x, NOISE, args.seed)
    band = fdi_band(pipe, band_signals, val_k, False)  # the full-flow band's FDI share, on top of the physics band
    if band is not None:
        pipe.fdi_deltas.copy_(band.deltas.to(pipe.fdi_deltas))
        pipe.fdi_direction.copy_(band.direction.to(pipe.fdi_direction))
        pipe.set_health_stop(band.health_stop)
    with torch.no_grad():
        _, score, _, ood, _ = pipe(band_signals.to(dtype))
    platt = verdict_scaling(None, score, ood, val_h)
    if platt is not None:
        pipe.verdict_scale.fill_(platt[0])
        pipe.verdict_offset.fill_(platt[1])
    with torch.no_grad():
        after = {
            "verdict_val": _rates(pipe(val_x.to(dtype))[1], val_h),
            "health_val": _rates(pipe.classifier(val_k.to(dtype)) - pipe.classifier.threshold, val_h),
        }
    # the phi_a its health classifier (the RUL event) learned, which phm-track compares with a life split's
    prior = {} if platt is None else {"verdict_prior_faulty": platt[2]}  # phm-track's verdict evidence reads it
    damage = {} if rul_k is None else {"damage": damage_meta}  # the law the band was calibrated with (phm-track)
    export_torchscript(pipe, args.out, {**metadata, "assessment": assessment, **prior, **damage})
    report = {
        "out": args.out,
        "before": before,
        "after": after,
        "fdi_band_deltas": None if band is None else band.deltas.tolist(),
        "verdict_platt": None if platt is None else list(platt[:2]),
        "classifier_fit": fit_report,
        "physics_band": physics,
    }
    Path(args.out).with_suffix(".refit.json").write_text(json.dumps(report, indent=2))
    print(json.dumps(report, indent=2))


if __name__ == "__main__":
    main()
