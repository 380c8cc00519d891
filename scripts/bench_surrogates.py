"""Benchmark of the surrogates on a dataset store; writes JSON.

Sections:

* ``classifier``: the torch-trained polynomial SVM (and the Nystrom RBF SVM) against scikit-learn's
  ``SVC`` (same polynomial kernel, same C, same standardised inputs; the baseline the issue asks for):
  accuracy, missed-fault and false-alarm rates on the validation split, fit time, single-vector and
  batched latency.
* ``fdi_latency``: single-signal latency of gappy POD + FDI network (eager; TorchScript) of a trained
  bundle (``--bundle``, e.g. results/train/surrogates.pt), the masked (missing-sample) path, the health
  score, and the batched throughput. Median of ``--repeats`` calls on one thread.
* ``pod``: POD fit time of the solvers on the training split.
* ``selectors``: coefficient error (median, IQR) clean and with 1 % noise, and the gappy condition
  number, of every selector at ``--n-modes`` / ``--n-points``.

scikit-learn is an optional dependency (``pip install -e ".[bench]"``); without it the SVC rows say so.

Usage: python scripts/bench_surrogates.py --data-dir data/quick [--bundle results/train/surrogates.pt]
           [--out results/bench_surrogates.json] [--n-modes 22] [--n-points 30] [--repeats 2000]
"""

from __future__ import annotations

import argparse
import json
import platform
import time
from pathlib import Path
from typing import Any

import torch

from phm_torch.surrogates import POD, GappyPOD, PolynomialSVM, SurrogateBundle, add_noise, confusion, err_alpha, rms
from phm_torch.surrogates.classifiers import RBFSVM
from phm_torch.surrogates.data import load_store
from phm_torch.surrogates.evaluate import latency_us, quartiles
from phm_torch.surrogates.selectors import SELECTORS, build_selector


def timed(fn: Any) -> tuple[Any, float]:
    t0 = time.perf_counter()
    out = fn()
    return out, time.perf_counter() - t0


def bench_classifiers(train: Any, val: Any, c: float, repeats: int) -> dict[str, Any]:
    out: dict[str, Any] = {"n_train": len(train), "n_val": len(val), "C": c}
    for name, clf in (("torch_poly_svm", PolynomialSVM(C=c)), ("torch_rbf_svm", RBFSVM(C=c))):
        _, fit_s = timed(lambda clf=clf: clf.fit(train.k, train.healthy))
        conf = confusion(clf.predict(val.k), val.healthy)
        with torch.inference_mode():
            lat = latency_us(lambda clf=clf: clf(val.k[:1]), repeats)
            _, batch_s = timed(lambda clf=clf: clf(val.k))
        out[name] = {
            "fit_s": fit_s,
            "latency_us_p50": lat,
            "batch_us_per_vector": batch_s / len(val) * 1e6,
            **{k: conf[k] for k in ("accuracy", "missed_fault_rate", "false_alarm_rate")},
        }
    try:
        from sklearn.svm import SVC
    except ModuleNotFoundError:
        out["sklearn_svc"] = {"skipped": "scikit-learn is not installed (pip install -e '.[bench]')"}
        return out
    mean, std = train.k.double().mean(0), train.k.double().std(0)
    x, xv = ((train.k.double() - mean) / std).numpy(), ((val.k.double() - mean) / std).numpy()
    svc = SVC(kernel="poly", degree=3, gamma=1.0 / 8, coef0=1.0, C=c)
    _, fit_s = timed(lambda: svc.fit(x, train.healthy.numpy()))
    pred = torch.from_numpy(svc.predict(xv)).bool()
    conf = confusion(pred, val.healthy)
    lat = latency_us(lambda: svc.decision_function(xv[:1]), max(repeats // 4, 50))
    out["sklearn_svc"] = {
        "fit_s": fit_s,
        "latency_us_p50": lat,
        "n_support": int(svc.n_support_.sum()),
        **{k: conf[k] for k in ("accuracy", "missed_fault_rate", "false_alarm_rate")},
    }
    return out


def bench_fdi(bundle_path: Path, val: Any, repeats: int) -> dict[str, Any]:
    bundle = SurrogateBundle.load(bundle_path)
    samples = bundle.compress(val.current)
    one = samples[:1].contiguous()
    holed = one.clone()
    holed[0, :3] = float("nan")
    k = val.k[:1]
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        with torch.inference_mode():
            scripted = torch.jit.script(bundle)
            res = {
                "bundle": str(bundle_path),
                "n_modes": bundle.pod.n_modes,
                "n_points": bundle.gappy.n_points,
                "n_hidden": bundle.network.n_hidden,
                "fdi_latency_us_p50": latency_us(lambda: bundle.fdi(one), repeats),
                "fdi_torchscript_latency_us_p50": latency_us(lambda: scripted(one), repeats),
                "fdi_missing3_latency_us_p50": latency_us(lambda: bundle.fdi(holed), repeats),
                "gappy_latency_us_p50": latency_us(lambda: bundle.coefficients(one), repeats),
                "health_score_latency_us_p50": latency_us(lambda: bundle.health_score(k), repeats),
            }
            _, batch_s = timed(lambda: bundle.fdi(samples))
            res["fdi_batch_us_per_signal"] = batch_s / samples.shape[0] * 1e6
    finally:
        torch.set_num_threads(threads)
    return res


def bench_pod(train: Any, n_modes: int) -> dict[str, Any]:
    out = {}
    for solver in ("snapshots", "randomized"):
        _, s = timed(lambda solver=solver: POD(n_modes, solver=solver).fit(train.current))
        out[f"{solver}_s"] = s
    return out


def bench_selectors(train: Any, val: Any, grid: torch.Tensor, n_modes: int, n_points: int) -> dict[str, Any]:
    pod = POD(n_modes).fit(train.current)
    alpha_full = pod(val.current)
    noisy_val = add_noise(val.current, rms(val.current), 0.01, torch.Generator().manual_seed(0))
    out = {}
    for name in sorted(SELECTORS):
        sel = build_selector(name, n_points=n_points)
        extra = {"snapshots": train.current, "mean": pod.mean_} if sel.needs_snapshots else {}
        _, fit_s = timed(lambda sel=sel, extra=extra: sel.fit(pod.modes_, grid, **extra))
        gappy = GappyPOD(pod.modes_, pod.mean_, sel.indices_)
        clean = quartiles(err_alpha(gappy(gappy.select(val.current))[0], alpha_full))
        noisy = quartiles(err_alpha(gappy(gappy.select(noisy_val))[0], alpha_full))
        out[name] = {
            "fit_s": fit_s,
            "condition_number": gappy.condition_number(),
            "err_alpha_median": clean["median"],
            "err_alpha_iqr": clean["iqr"],
            "err_alpha_median_noise": noisy["median"],
            "err_alpha_iqr_noise": noisy["iqr"],
        }
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data-dir", required=True, help="dataset store (phm-generate)")
    ap.add_argument("--bundle", default=None, help="trained surrogates.pt for the FDI latency section")
    ap.add_argument("--out", default="results/bench_surrogates.json")
    ap.add_argument("--n-modes", type=int, default=22)
    ap.add_argument("--n-points", type=int, default=30)
    ap.add_argument("--C", type=float, default=100.0, help="soft-margin penalty of every SVM")
    ap.add_argument("--repeats", type=int, default=2000)
    ap.add_argument("--skip", nargs="*", default=[], choices=["classifier", "fdi_latency", "pod", "selectors"])
    args = ap.parse_args()
    data, grid, info = load_store(args.data_dir, {"train": "train", "val": "val"})
    train, val = data["train"], data["val"]
    report: dict[str, Any] = {
        "data_dir": args.data_dir,
        "data_fingerprint": info["manifest"].get("fingerprint"),
        "machine": {
            "platform": platform.platform(),
            "processor": platform.processor(),
            "torch": torch.__version__,
            "threads": torch.get_num_threads(),
        },
    }
    if "classifier" not in args.skip:
        report["classifier"] = bench_classifiers(train, val, args.C, args.repeats)
    if "fdi_latency" not in args.skip and args.bundle:
        report["fdi_latency"] = bench_fdi(Path(args.bundle), val, args.repeats)
    if "pod" not in args.skip:
        report["pod"] = bench_pod(train, args.n_modes)
    if "selectors" not in args.skip:
        report["selectors"] = bench_selectors(train, val, grid, args.n_modes, args.n_points)
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    from phm_torch.io.atomic import atomic_open

    with atomic_open(out, "w") as fh:
        json.dump(report, fh, indent=2)
        fh.write("\n")
    print(json.dumps(report, indent=2))


if __name__ == "__main__":
    main()
