"""``phm-evaluate``: RUL on the ``rul`` split from the true k and from the full online flow, against the
physics reference; writes metrics.json, the figures, rul_calibration.json and the TorchScript pipeline.

The work is done by :func:`evaluate_rul` (a plain function of the composed config).
"""

from __future__ import annotations

import hashlib
import json
import logging
import time
from pathlib import Path
from typing import Any

import hydra
import torch
from omegaconf import DictConfig

from .. import provenance
from ..data.store import DatasetStore
from ..faults import FAULT_NAMES
from ..online import OnlinePipeline
from ..online.consistency import calibrate_consistency
from ..online.fdi_band import FDIBand, TooFewCalibrationSignals, calibrate_fdi_band
from ..online.fdi_interval import FDIInterval, calibrate_fdi_interval, interval_quality
from ..online.formats import check_formats, write_checked
from ..online.input_contract import tracking_range
from ..online.noise_threshold import calibrate_gappy_residual
from ..online.verdict import calibrate_verdict, shift_prior, verdict_quality
from ..params import ActuatorParams
from ..prognostics import DeterministicRUL, RULEstimator
from ..prognostics.evaluation import RULComparison
from ..prognostics.plots import error_panels, rul_vs_expected
from ..prognostics.reference import margin_score, reference_rul
from ..prognostics.rul import VARIANTS
from ..surrogates.augment import add_noise, rms
from ..surrogates.bundle import SurrogateBundle
from ..surrogates.metrics import IDENTIFIED_R2, fdi_identifiability
from . import common

log = logging.getLogger(__name__)


def _reference(
    cfg: DictConfig,
    assessment: Any,
    params: ActuatorParams,
    damage: Any,
    k: torch.Tensor,
    deltas: torch.Tensor,
    cache: Path,
) -> torch.Tensor:
    """Reference RULs, cached in ``cache`` under a key of everything they depend on."""
    key_data = {
        "damage": common.plain(cfg.damage),
        "assessment": common.plain(assessment),
        "actuator": provenance.actuator_values(params),
        "reference": common.plain(cfg.reference),
        "deltas": [round(float(d), 12) for d in deltas],
        "k": hashlib.sha256(k.numpy().tobytes()).hexdigest(),
    }
    key = hashlib.sha256(json.dumps(key_data, sort_keys=True).encode()).hexdigest()
    if cache.is_file():
        stored = json.loads(cache.read_text())
        if stored.get("key") == key:
            return torch.tensor(stored["rul"], dtype=torch.float64)
    assess = common.build(assessment, "assessment", params=params)
    ref = reference_rul(
        damage,
        margin_score(assess),
        k,
        deltas,
        common.number(cfg.reference.step_hours, "reference.step_hours", 0.0, strict=True),
        common.integer(cfg.reference.refine_iterations, "reference.refine_iterations", 0),
    )
    common.write_json(cache, {"key": key, "rul": ref.tolist()})
    return ref


def _noisy(cfg: DictConfig, signals: torch.Tensor) -> torch.Tensor:
    """The held-out calibration signals with ``fdi_band.noise`` relative measurement noise."""
    noise = common.number(cfg.fdi_band.noise, "fdi_band.noise", 0.0)
    if noise > 0 and signals.shape[0]:
        signals = add_noise(signals, rms(signals), noise, torch.Generator().manual_seed(int(cfg.seed) + 2))
    return signals


def _fdi_band(cfg: DictConfig, pipeline: OnlinePipeline, signals: torch.Tensor, k: torch.Tensor) -> FDIBand | None:
    """The FDI band calibrated on held-out (noisy) signals, or None (with a warning: the full-flow band is
    then the physics band only, too narrow) when too few are usable."""
    try:
        return calibrate_fdi_band(pipeline, signals, k, correct_median=bool(cfg.fdi_band.correct_median))
    except TooFewCalibrationSignals as err:
        log.warning("%s; the full-flow RUL band holds the physics spread only", err)
        return None


def _verdict_prior(cfg: DictConfig) -> float | None:
    prior = cfg.verdict.prior_faulty
    if prior is None:
        return None
    prior = common.number(prior, "verdict.prior_faulty", 0.0, strict=True)
    if prior >= 1.0:
        raise ValueError(f"verdict.prior_faulty must be in (0, 1), got {prior!r}")
    return prior


def _verdict(
    prior: float | None, score: torch.Tensor, ood: torch.Tensor, healthy: torch.Tensor
) -> tuple[float, float, float] | None:
    """Platt scaling (a, b) of the pipeline's health score on held-out (noisy) signals, moved to the fault
    rate ``prior`` (None: the signals' own), and that rate; or None (with a warning: the exported
    pipeline's P(faulty) is then NaN) when the signals are not two-class. ``score`` and ``ood`` (N,): the
    pipeline's outputs on them."""
    keep = ~ood & torch.isfinite(score)
    try:
        a, b = calibrate_verdict(score[keep], ~healthy[keep])
    except ValueError as err:
        log.warning("verdict not calibrated: %s", err)
        return None
    own = float((~healthy[keep]).double().mean())
    if prior is None:
        return a, b, own
    return a, shift_prior(b, own, prior), prior


def _identifiability(k_hat: torch.Tensor, k: torch.Tensor, ood: torch.Tensor) -> dict[str, float]:
    """R^2 of each component's estimate on the in-distribution calibration records {fault name: R^2}
    (:func:`~phm_torch.surrogates.metrics.fdi_identifiability`); a warning names those the test command does not
    identify, whose k_hat is mostly the training prior."""
    keep = ~ood
    r2 = (
        fdi_identifiability(k_hat[keep].to(torch.float64), k[keep].to(torch.float64))
        if int(keep.sum()) > 1
        else [float("nan")] * len(FAULT_NAMES)
    )
    out = {name: round(v, 4) for name, v in zip(FAULT_NAMES, r2)}
    weak = {name: v for name, v in out.items() if not v >= IDENTIFIED_R2}
    if weak:
        log.warning(
            "the test command does not identify %s (R^2 %s on held-out records, below %.2f): their k_hat is "
            "mostly the training prior; phm-predict lists them under k_not_identified",
            ", ".join(weak),
            ", ".join(f"{v:.2f}" for v in weak.values()),
            IDENTIFIED_R2,
        )
    return out


def _interval_settings(cfg: DictConfig) -> tuple[float, int, list[float]]:
    """(coverage, min_count, noise levels) of the k_hat intervals, checked before any work; the levels are
    ``fdi_band.noise`` (the calibration records') and the increasing ``fdi_interval.noise_levels`` above it."""
    coverage = common.number(cfg.fdi_interval.coverage, "fdi_interval.coverage", 0.0, strict=True)
    if coverage >= 1.0:
        raise ValueError(f"fdi_interval.coverage must be in (0, 1), got {coverage!r}")
    levels = [common.number(cfg.fdi_band.noise, "fdi_band.noise", 0.0)]
    extra = common.plain(cfg.fdi_interval.get("noise_levels")) or []
    if not isinstance(extra, list):
        raise ValueError(f"fdi_interval.noise_levels must be a list of noise levels, got {extra!r}")
    for i, value in enumerate(extra):
        level = common.number(value, f"fdi_interval.noise_levels[{i}]", 0.0, strict=True)
        if level <= levels[-1]:
            raise ValueError(
                f"fdi_interval.noise_levels[{i}] must exceed {levels[-1]!r} (fdi_band.noise and the "
                f"levels before it, increasing), got {level!r}"
            )
        levels.append(level)
    return coverage, common.integer(cfg.fdi_interval.min_count, "fdi_interval.min_count", 1), levels


def _fdi_interval(
    settings: tuple[float, int, list[float]],
    nominal: torch.Tensor,
    k_hat: torch.Tensor,
    ood: torch.Tensor,
    k: torch.Tensor,
) -> FDIInterval | None:
    """Conformal half-widths of the k_hat intervals from the pipeline's estimates k_hat (N, 8) and flags ood
    (N,) on held-out (noisy) signals of true fault vectors k (N, 8), or None (with a warning: the exported
    pipeline's intervals are then NaN) when too few are in distribution."""
    coverage, min_count, _ = settings
    if int((~ood).sum()) < min_count:
        log.warning(
            "k_hat intervals not calibrated: %d in-distribution records, fdi_interval.min_count=%d",
            int((~ood).sum()),
            min_count,
        )
        return None
    return calibrate_fdi_interval(k_hat[~ood], k[~ood].to(k_hat.dtype), nominal, coverage, min_count)


def _fdi_intervals(
    settings: tuple[float, int, list[float]],
    pipeline: OnlinePipeline,
    k_hat: torch.Tensor,
    ood: torch.Tensor,
    clean: torch.Tensor,
    k: torch.Tensor,
    seed: int,
) -> tuple[FDIInterval | None, list[float]]:
    """Calibrate the pipeline's k_hat intervals in place at every noise level of ``settings``: the first from
    the pipeline's outputs k_hat, ood on the (noisy) calibration signals, the others from the noise-free
    ``clean`` signals (N, n) with that level of noise added. Returns the first level's interval (None: not
    calibrated) and the levels calibrated."""
    interval = _fdi_interval(settings, pipeline.nominal, k_hat, ood, k)
    levels = settings[2][:1]
    if interval is None:
        return None, levels
    widths = [interval.half_widths]
    for i, level in enumerate(settings[2][1:]):
        noisy = add_noise(clean, rms(clean), level, torch.Generator().manual_seed(seed + 10 + i))
        with torch.no_grad():
            k_hat_l, _, _, ood_l, _ = pipeline(noisy.to(pipeline.times.dtype))
        more = _fdi_interval(settings, pipeline.nominal, k_hat_l, ood_l, k)
        if more is None:
            break
        widths.append(torch.maximum(more.half_widths, widths[-1]))  # never narrower with more noise
        levels.append(level)
    pipeline.k_half_widths = torch.stack(widths).to(pipeline.times.dtype)
    pipeline.interval_noise = torch.tensor(levels, dtype=pipeline.times.dtype)
    pipeline.interval_level = interval.level
    return interval, levels


def _tracking_ranges(store: DatasetStore, block_rows: int = 2048) -> tuple[list[float], list[float] | None]:
    """The tracking NRMSE range over every split with positions (train, val, rul; read in row blocks), and that of
    its healthy records: the input contract's position check (phm-predict). Every split, not the evaluated one
    alone: the rul split's 100 vectors spanned 0.109-0.118 on the paper store, a clean double short of the val
    design reads 0.19, and a motor with every phase shorted does not move at all (train: 0.08-0.49). The
    healthy range (0.08-0.19 there) is the one a record the pipeline calls healthy must meet: a dead or
    reversed position sensor on a healthy actuator is caught, on a faulty one it can be the fault itself."""
    command = torch.as_tensor(store.command)
    ranges: dict[bool, list[float]] = {}
    for name in store.splits:
        view = store.split(name)
        if "position" not in view.group or len(view) == 0:
            continue
        for start in range(0, len(view), block_rows):
            position = torch.as_tensor(view.position[start : start + block_rows])
            healthy = torch.as_tensor(view.healthy[start : start + block_rows]).bool()
            for key, rows in ((False, position), (True, position[healthy])):
                if rows.shape[0]:
                    lo, hi = tracking_range(command, rows)
                    old = ranges.get(key, [lo, hi])
                    ranges[key] = [min(old[0], lo), max(old[1], hi)]
    if False not in ranges:
        raise ValueError(f"store {store.data_dir}: no split holds positions (the input contract's tracking check)")
    return ranges[False], ranges.get(True)


def evaluate_rul(cfg: DictConfig) -> tuple[dict[str, Any], dict[str, Any]]:
    """Evaluate the RUL estimation (see :mod:`phm_torch.prognostics.evaluation` for the definitions)."""
    common.set_threads(cfg)
    prior = _verdict_prior(cfg)
    interval_settings = _interval_settings(cfg)
    formats = check_formats(common.plain(cfg.export_formats)) if cfg.export else []
    with DatasetStore(cfg.data_dir) as store:
        prov = common.reconcile_provenance(cfg, store.provenance, f"store {cfg.data_dir}")
        assessment = (
            cfg.assessment
            if cfg.get("assessment") is not None
            else (store.metadata.get("config") or {}).get("assessment")
        )
    if assessment is None:
        raise ValueError(
            f"assessment: store {cfg.data_dir} records no assessment config; choose one with "
            "assessment=frequency_response"
        )
    params = common.actuator_of(prov["actuator"], cfg)
    damage = common.build(cfg.damage, "damage", nominal=list(params.nominal_faults))
    out_dir = Path(cfg.out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    bundle = SurrogateBundle.load(cfg.bundle)
    provenance.require_same(bundle.provenance, prov, f"bundle {cfg.bundle}")  # trained on a store of the same
    band_split = str(cfg.fdi_band.split)
    if band_split == cfg.split:
        raise ValueError(
            f"fdi_band.split must differ from split (both {band_split!r}): the FDI band would be "
            "calibrated on the signals it is evaluated on"
        )
    with DatasetStore(cfg.data_dir) as store:
        view = store.split(cfg.split)
        k = torch.as_tensor(view.K[()], dtype=torch.float64)
        signals = torch.as_tensor(view.current[()], dtype=torch.float64)
        band_view = store.split(band_split)
        band_k = torch.as_tensor(band_view.K[()], dtype=torch.float64)
        band_clean = torch.as_tensor(band_view.current[()], dtype=torch.float64)
        band_signals = _noisy(cfg, band_clean)
        band_healthy = torch.as_tensor(band_view.healthy[()]).bool()
        healthy = torch.as_tensor(view.healthy[()]).bool()
        tracking, tracking_healthy = _tracking_ranges(store)
    if k.shape[0] == 0:
        raise ValueError(f"split {cfg.split!r} of {cfg.data_dir} is empty")
    t0 = time.perf_counter()
    est = RULEstimator(
        damage,
        bundle.health_score,
        common.integer(cfg.rul.n_samples, "rul.n_samples", 2),
        common.integer(cfg.rul.refine_iterations, "rul.refine_iterations", 0),
    )
    det = DeterministicRUL(est, str(cfg.rul.band))
    deltas = det.calibrate(
        k,
        torch.Generator().manual_seed(int(cfg.seed)),
        bracket=common.number(cfg.rul.delta_bracket, "rul.delta_bracket", 0.0, strict=True),
    )
    mc = est.estimate(k, torch.Generator().manual_seed(int(cfg.seed) + 1))
    min_present = common.number(cfg.online.min_present, "online.min_present", 0.0, True)
    pipelines = {}
    for variant in VARIANTS:  # the configured band is exported; the other one is reported
        pipe_deltas, scales = det.pipeline_parameters(variant)
        pipelines[variant] = OnlinePipeline.from_bundle(
            bundle, damage, pipe_deltas, det.direction, min_present, rate_scales=scales
        ).eval()
    pipeline = pipelines[det.variant]
    with torch.no_grad():  # k_hat does not depend on the band: what the command identifies, first
        band_k_hat, _, _, band_ood, _ = pipeline(band_signals.to(pipeline.times.dtype))
    identifiability = _identifiability(band_k_hat, band_k, band_ood)
    unidentified = [FAULT_NAMES.index(name) for name, r2 in identifiability.items() if not r2 >= IDENTIFIED_R2]
    pipeline.set_unidentified(unidentified)
    band = _fdi_band(cfg, pipeline, band_signals, band_k)
    if band is not None:
        pipeline.fdi_deltas.copy_(band.deltas.to(pipeline.fdi_deltas))
        pipeline.fdi_direction.copy_(band.direction.to(pipeline.fdi_direction))
        pipeline.set_health_stop(band.health_stop)
    with torch.no_grad():
        band_k_hat, band_score, _, band_ood, _ = pipeline(band_signals.to(pipeline.times.dtype))
    verdict = _verdict(prior, band_score, band_ood, band_healthy)
    if verdict is not None:
        pipeline.verdict_scale.fill_(verdict[0])
        pipeline.verdict_offset.fill_(verdict[1])
    calibration_noise = interval_settings[2][0]  # fdi_band.noise: the band signals' own
    pipeline.calibration_noise.fill_(calibration_noise)
    interval, noise_levels = _fdi_intervals(
        interval_settings, pipeline, band_k_hat, band_ood, band_clean, band_k, int(cfg.seed)
    )
    gappy_residual = calibrate_gappy_residual(
        pipeline,
        band_clean,
        interval_settings[2],
        int(cfg.seed),
        common.number(cfg.ood.quantile, "ood.quantile", 0.0, strict=True),
    )
    consistency = (
        calibrate_consistency(
            pipeline,
            band_clean,
            interval_settings[2],
            int(cfg.seed),
            common.number(cfg.consistency.quantile, "consistency.quantile", 0.0, strict=True),
        )
        if pipeline.has_consistency
        else None
    )
    with torch.no_grad():
        true_k = pipeline.rul(k.to(pipeline.times.dtype)).to(torch.float64)
        true_k_by_band = {v: p.rul(k.to(p.times.dtype)).to(torch.float64) for v, p in pipelines.items()}
        k_hat, score, full_flow, ood, _ = pipeline(signals)
        p_faulty = pipeline.faulty_probability(score)
        k_lower, k_upper = pipeline.k_interval(k_hat, pipeline.noise_level(signals))
        physics_only = pipeline.rul(k_hat).to(torch.float64)
        physics_only = torch.where(ood.unsqueeze(1), torch.full_like(physics_only, float("nan")), physics_only)
    t_est = time.perf_counter() - t0
    t0 = time.perf_counter()
    reference = _reference(
        cfg, assessment, params, damage, k, deltas, Path(cfg.data_dir) / f"rul_reference_{cfg.split}.json"
    )
    t_ref = time.perf_counter() - t0
    comparison = RULComparison(reference, true_k, full_flow.to(torch.float64))
    metrics: dict[str, Any] = comparison.metrics()
    gauss = RULComparison(reference, mc.gaussian, full_flow.to(torch.float64)).metrics()
    physics = RULComparison(reference, true_k, physics_only).metrics()
    usable = reference[:, 1] > 0
    ff = full_flow.to(torch.float64)[usable]
    finite = torch.isfinite(ff[:, 1]) & (ff[:, 1] > 0)
    metrics.update(
        rul_uncertainty_median_full_flow=float(((ff[:, 2] - ff[:, 0]) / ff[:, 1])[finite].median())
        if finite.any()
        else float("nan"),
        rul_band_coverage_full_flow_physics_only=physics["rul_band_coverage_full_flow"],
        rul_err_median_full_flow_physics_only=physics["rul_err_median_full_flow"],
        rul_band=det.variant,
        rate_scales=det.scales_.tolist(),
        **{
            f"rul_band_coverage_true_k_{v}": RULComparison(reference, b, full_flow.to(torch.float64)).metrics()[
                "rul_band_coverage_true_k"
            ]
            for v, b in true_k_by_band.items()
        },
        fdi_band_split=band_split,
        fdi_band_n_used=band.n_used if band else 0,
        fdi_band_deltas=pipeline.fdi_deltas.tolist() if band else None,  # as the pipeline holds them
        fdi_band_direction=pipeline.fdi_direction.tolist() if band else None,
        fdi_band_saturated=band.saturated if band else None,
        fdi_band_health_stop=band.health_stop if band else None,
        fdi_identifiability=identifiability,
        fdi_not_identified=[name for name, r2 in identifiability.items() if not r2 >= IDENTIFIED_R2],
        verdict_calibration=list(verdict[:2]) if verdict else None,
        verdict_prior_faulty=verdict[2] if verdict else None,
        **(
            {f"verdict_{key}": value for key, value in verdict_quality(p_faulty[~ood], ~healthy[~ood]).items()}
            if verdict and bool((~ood).any())
            else {}
        ),
        fdi_interval_half_widths=interval.half_widths.tolist() if interval else None,
        fdi_interval_half_widths_by_noise=pipeline.k_half_widths.tolist() if interval else None,
        fdi_interval_noise_levels=noise_levels if interval else None,
        fdi_interval_counts=interval.counts if interval else None,
        **(
            {
                f"fdi_interval_{key}": value
                for key, value in interval_quality(k_lower[~ood], k_upper[~ood], k[~ood].to(k_lower.dtype)).items()
            }
            if interval and bool((~ood).any())
            else {}
        ),
    )
    metrics.update(
        rul_err_median_true_k_monte_carlo=gauss["rul_err_median_true_k"],
        rul_band_coverage_true_k_monte_carlo=gauss["rul_band_coverage_true_k"],
        deltas=deltas.tolist(),
        deltas_saturated=det.saturated_,
        estimate_wall_s=round(t_est, 3),
        reference_wall_s=round(t_ref, 3),
        ood_fraction=float(ood.double().mean()),
        consistency=consistency,
        gappy_residual=gappy_residual,
    )
    figures = {
        "rul_vs_expected": rul_vs_expected(
            reference,
            {"RUL from true k": true_k, "full online flow": full_flow.to(torch.float64)},
            out_dir / "rul_vs_expected.png",
        ),
        "rul_errors": error_panels(reference, true_k, full_flow.to(torch.float64), out_dir / "rul_errors.png"),
    }
    common.write_json(
        out_dir / "rul_calibration.json",
        {
            "band": det.variant,
            "deltas": pipeline.deltas.tolist(),
            "direction": det.direction.tolist(),
            "rate_scales": pipeline.rate_scales.tolist(),
            "initial_state_deltas": deltas.tolist(),
            "fdi_deltas": pipeline.fdi_deltas.tolist(),
            "fdi_direction": pipeline.fdi_direction.tolist(),
            "fdi_health_stop": pipeline.health_stop_index.tolist(),
            "identifiability": identifiability,
            "fdi_unidentified": unidentified,
            "verdict": list(verdict[:2]) if verdict else None,
            "verdict_prior_faulty": verdict[2] if verdict else None,
            "fdi_interval": {
                "half_widths": pipeline.k_half_widths.tolist(),
                "noise_levels": noise_levels,
                "level": interval.level,
                "coverage": interval.coverage,
            }
            if interval
            else None,
            "calibration_noise": calibration_noise,
            "tracking_nrmse": tracking,
            "tracking_nrmse_healthy": tracking_healthy,
            "consistency": consistency,
            "gappy_residual": gappy_residual,
            "damage": common.plain(cfg.damage),
            "provenance": prov,
        },
    )
    common.write_json(
        out_dir / "rul_predictions.json",
        {
            "k": k.tolist(),
            "k_hat": k_hat.tolist(),
            "reference": reference.tolist(),
            "true_k": true_k.tolist(),
            "full_flow": torch.nan_to_num(full_flow, nan=-1.0).tolist(),
            "out_of_distribution": ood.tolist(),
        },
    )
    if cfg.export:  # each format of export_formats beside online.pt, reloaded and compared with eager
        checked = write_checked(
            pipeline,
            out_dir / "online.pt",
            formats,
            {
                "provenance": prov,
                "tracking_nrmse": tracking,
                "tracking_nrmse_healthy": tracking_healthy,
                "identifiability": identifiability,
                "damage": common.plain(cfg.damage),
            },
            signals[:8],
        )  # phm-track's process model
        metrics["export_max_abs_diff"] = max(checked["max_abs_diff"].values())
        metrics["export"] = next(iter(checked["files"].values()))
        metrics["export_files"], metrics["export_max_abs_diff_by_format"] = checked["files"], checked["max_abs_diff"]
    metrics.update(actuator=provenance.describe(prov["actuator"]), command=provenance.describe(prov["command"]))
    common.write_json(out_dir / "metrics.json", metrics)
    return metrics, {"pipeline": pipeline, "comparison": comparison, "figures": figures, "reference": reference}


@hydra.main(config_path=common.CONFIG_PATH, config_name="evaluate", version_base="1.3")
@common.report_errors("phm-evaluate")
def main(cfg: DictConfig) -> None:
    metrics, _ = evaluate_rul(cfg)
    print(json.dumps(metrics, indent=2), flush=True)


if __name__ == "__main__":
    main()
