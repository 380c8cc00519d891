"""The evaluation pipeline: RUL on the evaluated split from the true k and from the full online flow against
the physics reference, and the calibration of the exported pipeline's uncertainty on the held-out split.

:func:`evaluate_rul` is a plain function of :class:`~.settings.EvaluateSettings`; ``phm-evaluate``
(:mod:`phm_torch.apps.evaluate`) composes the settings, calls it and writes what it returns.
"""

from __future__ import annotations

import hashlib
import json
import logging
import time
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import torch

from ... import provenance
from ...checks import build
from ...faults import FAULT_NAMES
from ...io.atomic import write_json
from ...online import OnlinePipeline
from ...online.consistency import calibrate_consistency
from ...online.export import calibration_metadata
from ...online.fdi_interval import interval_quality
from ...online.input_contract import calibrate_shape_min
from ...online.noise_threshold import calibrate_gappy_residual
from ...online.spike_check import calibrate_spike_step
from ...online.timing_check import calibrate_timing_ratio
from ...online.unexplained_check import calibrate_ratio
from ...online.verdict import verdict_quality
from ...params import ActuatorParams
from ...prognostics import DeterministicRUL, RULEstimator
from ...prognostics.crossings import crossing_metrics, reference_crossings
from ...prognostics.evaluation import RULComparison
from ...prognostics.plots import error_panels, rul_vs_expected
from ...prognostics.reference import margin_score, reference_rul
from ...prognostics.rul import VARIANTS
from ...surrogates.metrics import IDENTIFIED_R2
from .calibration import fdi_band, fdi_intervals, identifiability, verdict_scaling
from .inputs import read_inputs
from .near_nominal import near_nominal_calibration
from .quality import held_out_quality
from .settings import EvaluateSettings

log = logging.getLogger(__name__)


def reference_ruls(
    settings: EvaluateSettings,
    assessment: Any,
    params: ActuatorParams,
    damage: Any,
    k: torch.Tensor,
    deltas: torch.Tensor,
    cache: Path,
) -> torch.Tensor:
    """Reference RULs, cached in ``cache`` under a key of everything they depend on."""
    key_data = {
        "damage": dict(settings.damage),
        "assessment": assessment,
        "actuator": provenance.actuator_values(params),
        "reference": settings.reference.as_dict(),
        "deltas": [round(float(d), 12) for d in deltas],
        "k": hashlib.sha256(k.numpy().tobytes()).hexdigest(),
    }
    key = hashlib.sha256(json.dumps(key_data, sort_keys=True).encode()).hexdigest()
    if cache.is_file():
        stored = json.loads(cache.read_text())
        if stored.get("key") == key:
            return torch.tensor(stored["rul"], dtype=torch.float64)
    assess = build(assessment, "assessment", params=params)
    ref = reference_rul(
        damage,
        margin_score(assess),
        k,
        deltas,
        settings.reference.step_hours,
        settings.reference.refine_iterations,
    )
    write_json(cache, {"key": key, "rul": ref.tolist()})
    return ref


def evaluate_rul(settings: EvaluateSettings) -> tuple[dict[str, Any], dict[str, Any]]:
    """Evaluate the RUL estimation (see :mod:`phm_torch.prognostics.evaluation` for the definitions) and
    calibrate the online pipeline's uncertainty on the held-out split.

    Returns:
        ``metrics`` and ``objects``: ``pipeline`` (the calibrated :class:`OnlinePipeline`), ``comparison``,
        ``figures`` (written under ``out_dir``), ``reference``, ``calibration`` (rul_calibration.json's
        content), ``predictions`` (rul_predictions.json's), ``provenance``, ``export_metadata`` (what the
        exported files carry besides the pipeline) and ``probe`` (records the exported files are checked on).
    """
    cal = settings.calibration
    inp = read_inputs(settings)
    out_dir = settings.out_dir
    out_dir.mkdir(parents=True, exist_ok=True)
    prov, assessment, params, damage, bundle = inp.prov, inp.assessment, inp.params, inp.damage, inp.bundle
    k, signals, healthy = inp.k, inp.signals, inp.healthy
    t0 = time.perf_counter()
    est = RULEstimator(damage, bundle.health_score, settings.rul.n_samples, settings.rul.refine_iterations)
    det = DeterministicRUL(est, settings.rul.band)
    deltas = det.calibrate(k, torch.Generator().manual_seed(settings.seed), bracket=settings.rul.delta_bracket)
    mc = est.estimate(k, torch.Generator().manual_seed(settings.seed + 1))
    min_present = settings.min_present
    pipelines = {}
    for variant in VARIANTS:  # the configured band is exported; the other one is reported
        pipe_deltas, scales = det.pipeline_parameters(variant)
        pipelines[variant] = OnlinePipeline.from_bundle(
            bundle, damage, pipe_deltas, det.direction, min_present, rate_scales=scales
        ).eval()
    pipeline = pipelines[det.variant]
    c = _calibrate(settings, pipeline, inp)
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
    reference = reference_ruls(
        settings,
        assessment,
        params,
        damage,
        k,
        deltas,
        Path(settings.data_dir) / f"rul_reference_{settings.split}.json",
    )
    t_ref = time.perf_counter() - t0
    comparison = RULComparison(reference, true_k, full_flow.to(torch.float64))
    metrics: dict[str, Any] = comparison.metrics()
    # how the reference crossings happen: the RUL from the true k cannot place a jump of phi_a's score
    score = margin_score(build(assessment, "assessment", params=params))
    metrics.update(crossing_metrics(reference, true_k, reference_crossings(damage, score, k, deltas[1], reference)))
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
        **_uncertainty_metrics(pipeline, c, cal.split, p_faulty, ood, healthy, k_lower, k_upper, k),
    )
    metrics.update(
        rul_err_median_true_k_monte_carlo=gauss["rul_err_median_true_k"],
        rul_band_coverage_true_k_monte_carlo=gauss["rul_band_coverage_true_k"],
        deltas=deltas.tolist(),
        deltas_saturated=det.saturated_,
        estimate_wall_s=round(t_est, 3),
        reference_wall_s=round(t_ref, 3),
        ood_fraction=float(ood.double().mean()),
        consistency=c.consistency,
        gappy_residual=c.gappy_residual,
    )
    figures = {
        "rul_vs_expected": rul_vs_expected(
            reference,
            {"RUL from true k": true_k, "full online flow": full_flow.to(torch.float64)},
            out_dir / "rul_vs_expected.png",
        ),
        "rul_errors": error_panels(reference, true_k, full_flow.to(torch.float64), out_dir / "rul_errors.png"),
    }
    metrics["held_out_quality"] = held_out_quality(pipeline, inp.band_signals, inp.band_healthy, cal.split, metrics)
    calibration = _calibration_record(settings, pipeline, det, deltas, c, inp)
    calibration["held_out_quality"] = metrics["held_out_quality"]  # exported with the pipeline (phm-predict reads it)
    predictions = {
        "k": k.tolist(),
        "k_hat": k_hat.tolist(),
        "reference": reference.tolist(),
        "true_k": true_k.tolist(),
        "full_flow": torch.nan_to_num(full_flow, nan=-1.0).tolist(),
        "out_of_distribution": ood.tolist(),
    }
    metrics.update(actuator=provenance.describe(prov["actuator"]), command=provenance.describe(prov["command"]))
    metrics["calibration_beyond_drive_range"] = inp.band_beyond_drive_range  # left out of every calibration
    metrics["shape_correlation_min"] = c.shape_min
    metrics["near_nominal_calibration_rows"] = c.near_rows
    brier, base = metrics.get("verdict_brier"), metrics.get("verdict_brier_base_rate")
    if brier is not None and base is not None and brier > base:
        # a P(faulty) no better than a constant: say so, the verdict's probabilities are not to be read as such
        log.warning(
            "P(faulty) scores a Brier of %.3f on the evaluated (rul) records, worse than their constant faulty "
            "fraction's %.3f: on records like these the verdict's probability carries no information; read the "
            "verdict with its RUL band and the k_hat intervals",
            brier,
            base,
        )
    metrics["unexplained_ratio_max"] = c.unexplained
    metrics["spike_step_max"] = c.spike_step
    metrics["timing_ratio_max"] = c.timing
    export_metadata = {
        "provenance": prov,
        **calibration_metadata(calibration),  # as phm-export writes them: verdict_prior_faulty included
        "identifiability": c.r2,
        "drive_current_bound": inp.bundle.extra.get("drive_current_bound"),  # the input contract's overcurrent
        "assessment": inp.bundle.extra.get("assessment"),  # the phi_a its classifiers learned (phm-track checks it)
        "damage": dict(settings.damage),  # phm-track's process model
    }
    return metrics, {
        "pipeline": pipeline,
        "comparison": comparison,
        "figures": figures,
        "reference": reference,
        "calibration": calibration,
        "predictions": predictions,
        "provenance": prov,
        "export_metadata": export_metadata,
        "probe": signals[:8],
    }


TIMING_RECORDS = 300  # held-out records the timing check's threshold is calibrated on


def _calibrate(settings: EvaluateSettings, pipeline: OnlinePipeline, inp: SimpleNamespace) -> SimpleNamespace:
    """Calibrate the exported pipeline's uncertainty in place on the held-out split, in order: identifiability (the
    95 % start of unidentified components), the FDI band, P(faulty), the k_hat intervals per noise level, the gappy
    residual and consistency thresholds."""
    cal = settings.calibration
    band_signals, band_k, band_clean, band_healthy = inp.band_signals, inp.band_k, inp.band_clean, inp.band_healthy
    with torch.no_grad():  # k_hat does not depend on the band: what the command identifies, first
        band_k_hat, _, _, band_ood, _ = pipeline(band_signals.to(pipeline.times.dtype))
    r2 = identifiability(band_k_hat, band_k, band_ood)
    unidentified = [FAULT_NAMES.index(name) for name, value in r2.items() if not value >= IDENTIFIED_R2]
    pipeline.set_unidentified(unidentified)
    band = fdi_band(pipeline, band_signals, band_k, cal.correct_median)
    if band is not None:
        pipeline.fdi_deltas.copy_(band.deltas.to(pipeline.fdi_deltas))
        pipeline.fdi_direction.copy_(band.direction.to(pipeline.fdi_direction))
        pipeline.set_health_stop(band.health_stop)
    with torch.no_grad():
        band_k_hat, band_score, _, band_ood, _ = pipeline(band_signals.to(pipeline.times.dtype))
    verdict = verdict_scaling(cal.prior_faulty, band_score, band_ood, band_healthy)
    if verdict is not None:
        pipeline.verdict_scale.fill_(verdict[0])
        pipeline.verdict_offset.fill_(verdict[1])
    calibration_noise = cal.noise  # the band signals' own
    pipeline.calibration_noise.fill_(calibration_noise)
    interval, noise_levels = fdi_intervals(
        cal, pipeline, band_k_hat, band_ood, band_clean, band_k, settings.seed, unidentified
    )
    levels = list(cal.noise_levels)
    gappy_residual = calibrate_gappy_residual(pipeline, band_clean, levels, settings.seed, cal.ood_quantile)
    consistency = (
        calibrate_consistency(pipeline, band_clean, levels, settings.seed, cal.consistency_quantile)
        if pipeline.has_consistency
        else None
    )
    held_out = SimpleNamespace(signals=band_signals, k=band_k, k_hat=band_k_hat, ood=band_ood)
    bound = inp.bundle.extra.get("drive_current_bound")
    near = near_nominal_calibration(
        pipeline,
        held_out,
        inp.training_k,
        inp.read_training,
        cal.noise,
        settings.seed,
        None if bound is None else float(bound),
    )
    return SimpleNamespace(
        r2=r2,
        shape_min=calibrate_shape_min(pipeline, near.signals, near.k_hat),
        unexplained=calibrate_ratio(pipeline, near.signals, near.k_hat),
        spike_step=calibrate_spike_step(pipeline, near.signals, near.k_hat),
        # after the consistency thresholds: the scan reads their statistic (in-distribution held-out records, the
        # first TIMING_RECORDS: ~20 ms each on the reference, coarse to fine)
        timing=calibrate_timing_ratio(pipeline, band_signals[~band_ood][:TIMING_RECORDS], pipeline.sample_rate),
        near_rows={"held_out": near.held_out, "training": near.training},
        unidentified=unidentified,
        band=band,
        verdict=verdict,
        calibration_noise=calibration_noise,
        interval=interval,
        noise_levels=noise_levels,
        gappy_residual=gappy_residual,
        consistency=consistency,
    )


def _uncertainty_metrics(
    pipeline: OnlinePipeline,
    c: SimpleNamespace,
    split: str,
    p_faulty: torch.Tensor,
    ood: torch.Tensor,
    healthy: torch.Tensor,
    k_lower: torch.Tensor,
    k_upper: torch.Tensor,
    k: torch.Tensor,
) -> dict[str, Any]:
    """The calibration's metrics: the FDI band, identifiability, P(faulty) and the k_hat intervals (their quality
    on the evaluated split's in-distribution records)."""
    band, verdict, interval, r2, noise_levels = c.band, c.verdict, c.interval, c.r2, c.noise_levels
    return dict(
        fdi_band_split=split,
        fdi_band_n_used=band.n_used if band else 0,
        fdi_band_deltas=pipeline.fdi_deltas.tolist() if band else None,  # as the pipeline holds them
        fdi_band_direction=pipeline.fdi_direction.tolist() if band else None,
        fdi_band_saturated=band.saturated if band else None,
        fdi_band_health_stop=band.health_stop if band else None,
        fdi_identifiability=r2,
        fdi_not_identified=[name for name, value in r2.items() if not value >= IDENTIFIED_R2],
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


def _calibration_record(
    settings: EvaluateSettings,
    pipeline: OnlinePipeline,
    det: DeterministicRUL,
    deltas: torch.Tensor,
    c: SimpleNamespace,
    inp: SimpleNamespace,
) -> dict[str, Any]:
    """rul_calibration.json: what phm-export needs to rebuild the calibrated pipeline from the bundle."""
    interval = c.interval
    return {
        "band": det.variant,
        "deltas": pipeline.deltas.tolist(),
        "direction": det.direction.tolist(),
        "rate_scales": pipeline.rate_scales.tolist(),
        "initial_state_deltas": deltas.tolist(),
        "fdi_deltas": pipeline.fdi_deltas.tolist(),
        "fdi_direction": pipeline.fdi_direction.tolist(),
        "fdi_health_stop": pipeline.health_stop_index.tolist(),
        "identifiability": c.r2,
        "fdi_unidentified": c.unidentified,
        "verdict": list(c.verdict[:2]) if c.verdict else None,
        "verdict_prior_faulty": c.verdict[2] if c.verdict else None,
        "fdi_interval": {
            "half_widths": pipeline.k_half_widths.tolist(),
            "noise_levels": c.noise_levels,
            "level": interval.level,
            "coverage": interval.coverage,
        }
        if interval
        else None,
        "calibration_noise": c.calibration_noise,
        "tracking_nrmse": inp.tracking,
        "tracking_nrmse_healthy": inp.tracking_healthy,
        "shape_correlation_min": c.shape_min,
        "unexplained_ratio_max": c.unexplained,
        "spike_step_max": c.spike_step,
        "timing_ratio_max": c.timing,
        "consistency": c.consistency,
        "gappy_residual": c.gappy_residual,
        "damage": dict(settings.damage),
        "provenance": inp.prov,
    }
