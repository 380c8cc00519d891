"""A tracker for an exported pipeline: its damage law (metadata, or the composed conf/damage for an older
pipeline), checked against its propagators, and the per-particle RUL with its own physics band."""

from __future__ import annotations

import logging
from collections.abc import Mapping
from typing import Any

from ..online.diagnosis import not_identified
from .damage_law import DamageLaw, band_includes_rate_scale, damage_config
from .inspection import require_calibrated
from .particle_filter import Tracker
from .particle_rul import ParticleRUL, eps_log_sigmas
from .response import FDIResponse
from .tracker_settings import TrackerSettings

log = logging.getLogger(__name__)


def build_tracker(
    model: Any,
    metadata: Mapping[str, Any],
    fallback_damage: Mapping[str, Any] | None,
    settings: TrackerSettings,
    source: str,
    response: FDIResponse | None = None,
) -> tuple[Tracker, dict[str, Any]]:
    """(tracker, description) for the pipeline ``model`` with metadata ``metadata`` (:func:`read_metadata`).

    The pipeline's own RUL band (``rate_scales``) is the future-eps spread. Whether that band already holds the
    spread of s depends on the law it was calibrated with (the metadata's ``damage``, which phm-evaluate and
    phm-export copy from the calibration): since the rate scale exists, the Monte Carlo RUL draws one s per run
    when the config's ``rate_scale_sigma`` > 0, and that share is removed (:func:`~.particle_rul.eps_log_sigmas`);
    a config without the key was calibrated before, with eps alone. The shipped pipeline has no damage config at
    all (the composed ``conf/damage`` stands in, with a warning), and was calibrated before too. The prior of s
    (the tracking) is the law's ``rate_scale_sigma``, or the composed config's where the pipeline's has none.
    The fault rate its P(faulty) was calibrated at (``verdict_prior_faulty``) turns each record's P(faulty) into a
    likelihood ratio (:func:`~.measurement.verdict_odds`). ``response``: the FDI's response near nominal of ``model``
    (:func:`~.companions.companion` loads and checks it), inverted before each k_hat is fused (:mod:`.response`).
    The description (JSON) names the law's source, the band, that rate and the components the response moves."""
    require_calibrated(model, source)
    damage, where = damage_config(metadata, fallback_damage, source)
    calibrated_sigma = damage.get("rate_scale_sigma")
    if calibrated_sigma is None and fallback_damage is not None and fallback_damage.get("rate_scale_sigma"):
        log.warning(
            "%s: its damage config predates the wear-rate scale; s is tracked with the composed "
            "conf/damage's prior (rate_scale_sigma %s), its RUL band read as eps alone",
            source,
            fallback_damage["rate_scale_sigma"],
        )
        damage = {**damage, "rate_scale_sigma": fallback_damage["rate_scale_sigma"]}
    law = DamageLaw.from_config(damage, model, where)
    with_s = band_includes_rate_scale(metadata)
    eps = eps_log_sigmas(model, law, with_s)
    rul = ParticleRUL(model, law, settings.max_rate_scale, settings.bisections, eps, settings.boundary_std_hours)
    prior = metadata.get("verdict_prior_faulty")
    if settings.verdict_evidence and prior is None:
        log.info(
            "%s records no verdict_prior_faulty (exported before phm-export copied it): the records' own verdicts "
            "are not weighed into the RUL",
            source,
        )
    unread = not_identified(metadata)
    if unread:
        log.info(
            "%s does not identify %s (R^2 below 0.25 on held-out records): they are not fused; the filter holds them "
            "at the damage law's prediction from new",
            source,
            ", ".join(unread),
        )
    tracker = Tracker(law, rul, settings, None if prior is None else float(prior), response, unread)
    return tracker, {
        "damage": damage,
        "damage_source": where,
        "rate_scale_sigma": law.rate_scale_sigma,
        "eps_log_sigmas": list(eps),
        "band_included_rate_scale": with_s,
        "verdict_prior_faulty": tracker.verdict_prior,
        "not_fused": unread,
        "fdi_response": None if response is None else {"corrected": response.corrected, **response.pipeline},
    }
