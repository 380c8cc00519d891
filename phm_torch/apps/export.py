"""``phm-export``: the online pipeline in one or several deployment formats (``format=torchscript`` by default,
``format=[torchscript,export,aoti]``; see :mod:`phm_torch.online.formats`), each reloaded and compared with eager.
Built from a surrogate bundle and its RUL calibration, or (``pipeline=<file.pt>``) rewritten from a TorchScript
pipeline file (:mod:`phm_torch.online.from_torchscript`)."""

from __future__ import annotations

import json
import logging
from pathlib import Path
from typing import Any

import hydra
import torch
from omegaconf import DictConfig

from .. import provenance
from ..online import OnlinePipeline
from ..online.export import calibration_metadata, read_metadata
from ..online.formats import check_dtype, check_formats, in_dtype, write_checked
from ..online.from_torchscript import rewrite_pipeline
from ..surrogates.bundle import SurrogateBundle
from . import common

log = logging.getLogger(__name__)


def _verdict(cal: dict[str, Any], path: Path) -> tuple[float, float] | None:
    """(a, b) of the verdict's Platt scaling from the calibration file; None (P(faulty) NaN) if it has none."""
    verdict = cal.get("verdict")
    if verdict is None:
        log.warning(
            "calibration %s has no verdict scaling (written by phm-evaluate since it exists): the "
            "pipeline's P(faulty) is NaN",
            path,
        )
        return None
    if not (isinstance(verdict, list) and len(verdict) == 2 and all(isinstance(v, (int, float)) for v in verdict)):
        raise ValueError(f"calibration {str(path)!r}: verdict must be [a, b], got {verdict!r}")
    return float(verdict[0]), float(verdict[1])


def _fdi_interval(cal: dict[str, Any], path: Path) -> dict[str, Any]:
    """Pipeline arguments of the k_hat intervals from the calibration file; {} (intervals NaN) if it has none."""
    interval = cal.get("fdi_interval")
    if interval is None:
        log.warning(
            "calibration %s has no k_hat intervals (written by phm-evaluate since they exist): the "
            "pipeline's k_interval is NaN",
            path,
        )
        return {}
    widths = interval.get("half_widths") if isinstance(interval, dict) else None
    level = interval.get("level") if isinstance(interval, dict) else None
    try:
        tensor = torch.tensor(widths, dtype=torch.float64)
    except (TypeError, ValueError, RuntimeError):
        tensor = None
    levels = interval.get("noise_levels") if isinstance(interval, dict) else None
    if (
        tensor is None
        or tensor.dim() not in (2, 3)
        or tensor.shape[-1] != 8
        or not isinstance(level, (int, float))
        or not level > 0
        or (tensor.dim() == 3 and not (isinstance(levels, list) and len(levels) == tensor.shape[0]))
    ):
        raise ValueError(
            f"calibration {str(path)!r}: fdi_interval must be {{half_widths: [n_levels][n_classes][8], "
            f"noise_levels: [n_levels], level: > 0}} (or half_widths [n_classes][8]), got {interval!r}"
        )
    out: dict[str, Any] = {"k_half_widths": tensor, "interval_level": float(level)}
    if tensor.dim() == 3:
        out["interval_noise"] = torch.tensor(levels, dtype=torch.float64)
    return out


def _calibration_noise(cal: dict[str, Any], path: Path) -> float | None:
    """Relative noise of the calibration records, or None (unknown: older calibration files)."""
    noise = cal.get("calibration_noise")
    if noise is None:
        return None
    if isinstance(noise, bool) or not isinstance(noise, (int, float)) or not noise >= 0:
        raise ValueError(f"calibration {str(path)!r}: calibration_noise must be a number >= 0, got {noise!r}")
    return float(noise)


def _damage(cal: dict[str, Any], cfg: DictConfig, path: Path) -> dict[str, Any]:
    """The damage config for the pipeline's metadata: the calibration's (the law its RUL band was calibrated
    with), warned about when its law differs from the composed one the propagators are built from."""
    composed = common.plain(cfg.damage)
    damage = cal.get("damage")
    if damage is None:
        return composed
    if not isinstance(damage, dict):
        raise ValueError(f"calibration {str(path)!r}: damage must be a mapping (the damage config), got {damage!r}")
    differ = [
        key
        for key in ("rate", "noise_std", "noise_correlation_hours", "rate_scale_sigma")
        if damage.get(key) != composed.get(key)
    ]
    if differ:
        log.warning(
            "calibration %s was made with another damage law than the composed one (%s differ): the "
            "pipeline's propagators follow the composed law, its metadata and RUL band the calibration's",
            path,
            ", ".join(differ),
        )
    return damage


def _rewrite(cfg: DictConfig, formats: list[str]) -> tuple[dict[str, Any], dict[str, Any]]:
    """``pipeline=<file.pt>``: the TorchScript file's pipeline in ``formats``, its metadata kept (an explicit
    ``actuator=``/``command=`` must match its provenance); bundle, calibration, damage and min_present unused."""
    source = Path(cfg.pipeline)
    recorded = read_metadata(source) if source.is_file() else {}
    prov = common.reconcile_provenance(cfg, recorded.get("provenance"), f"pipeline {source}")
    done = rewrite_pipeline(
        source, cfg.out, formats, {"provenance": prov} if any(prov.values()) else None, dtype=cfg.get("dtype")
    )
    by_format = done["max_abs_diff_by_format"]
    return {
        "out": next(iter(done["files"].values())),
        "files": done["files"],
        "source": str(source),
        "max_abs_diff_input": done["max_abs_diff_input"],
        "max_scaled_diff_input": done["max_scaled_diff_input"],
        "max_abs_diff_reloaded": max(by_format.values()),
        "max_abs_diff_by_format": by_format,
        "derived": done["derived"],
        "actuator": provenance.describe(prov["actuator"]) if prov["actuator"] else None,
        "command": provenance.describe(prov["command"]) if prov["command"] else None,
    }, {}


def export(cfg: DictConfig) -> tuple[dict[str, Any], dict[str, Any]]:
    """Build the pipeline from the bundle, the damage model and the RUL calibration (or rewrite the TorchScript
    ``pipeline``); write and re-check it."""
    formats = check_formats(common.plain(cfg.format))
    check_dtype(cfg.get("dtype"))  # before the bundle is read
    if cfg.get("pipeline") is not None:
        return _rewrite(cfg, formats)
    bundle = SurrogateBundle.load(cfg.bundle)
    cal_path = Path(cfg.calibration)
    if not cal_path.is_file():
        raise ValueError(
            f"calibration: no such file {str(cal_path)!r}; run phm-evaluate first (it writes rul_calibration.json)"
        )
    cal = json.loads(cal_path.read_text())
    for key in ("deltas", "direction"):
        if key not in cal:
            raise ValueError(f"calibration {str(cal_path)!r} has no {key!r}")
    prov = common.reconcile_provenance(cfg, bundle.provenance or None, f"bundle {cfg.bundle}")
    provenance.require_same(cal.get("provenance"), prov, f"calibration {cal_path}")  # a run on the same
    damage = common.build(cfg.damage, "damage", nominal=list(common.actuator_of(prov["actuator"], cfg).nominal_faults))
    fdi = {key: torch.tensor(cal[key]) for key in ("fdi_deltas", "fdi_direction") if key in cal}
    if len(fdi) < 2:
        log.warning(
            "calibration %s has no FDI band (fdi_deltas, fdi_direction; written by phm-evaluate since "
            "the band exists): the RUL bounds hold the physics spread only",
            cal_path,
        )
    pipeline = OnlinePipeline.from_bundle(
        bundle,
        damage,
        torch.tensor(cal["deltas"]),
        torch.tensor(cal["direction"]),
        common.number(cfg.min_present, "min_present", 0.0, strict=True),
        fdi.get("fdi_deltas"),
        fdi.get("fdi_direction"),
        torch.tensor(cal["rate_scales"]) if "rate_scales" in cal else None,
        verdict=_verdict(cal, cal_path),
        **_fdi_interval(cal, cal_path),
        calibration_noise=_calibration_noise(cal, cal_path),
        consistency=cal.get("consistency"),
        residual_limits=cal.get("gappy_residual"),
        fdi_health_stop=cal.get("fdi_health_stop"),
        unidentified=cal.get("fdi_unidentified"),
    )
    if pipeline.has_consistency and cal.get("consistency") is None:
        log.warning(
            "calibration %s has no consistency thresholds (phm-evaluate writes them for a bundle with a "
            "forward surrogate): the consistency check never flags",
            cal_path,
        )
    out = Path(cfg.out)
    extra = calibration_metadata(cal)
    extra["damage"] = _damage(cal, cfg, cal_path)  # the tracker's process model (phm-track)
    for key in ("drive_current_bound", "assessment"):  # the input contract's overcurrent; phm-track's phi_a check
        if bundle.extra.get(key) is not None:
            extra[key] = bundle.extra[key]
    pipeline = in_dtype(pipeline, cfg.get("dtype"))
    probe = bundle.pod.mean_.unsqueeze(0).to(pipeline.times.dtype)  # each file reloaded as phm-predict reads it
    checked = write_checked(pipeline, out, formats, {"provenance": prov, **extra}, probe)
    diffs = checked["max_abs_diff"]
    return {
        "out": next(iter(checked["files"].values())),
        "files": checked["files"],
        "max_abs_diff_reloaded": max(diffs.values()),
        "max_abs_diff_by_format": diffs,
        "actuator": provenance.describe(prov["actuator"]),
        "command": provenance.describe(prov["command"]),
    }, {"pipeline": pipeline}


@hydra.main(config_path=common.CONFIG_PATH, config_name="export", version_base="1.3")
@common.report_errors("phm-export")
def main(cfg: DictConfig) -> None:
    metrics, _ = export(cfg)
    print(json.dumps(metrics, indent=2), flush=True)


if __name__ == "__main__":
    main()
