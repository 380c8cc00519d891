"""A tracker for an exported pipeline: its damage law (metadata, or the composed conf/damage for an older
pipeline), checked against its propagators, and the per-particle RUL with its own physics band."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

from .damage_law import DamageLaw, damage_config
from .inspection import require_calibrated
from .particle_filter import Tracker, TrackerSettings
from .particle_rul import ParticleRUL, eps_log_sigmas


def build_tracker(model: Any, metadata: Mapping[str, Any], fallback_damage: Mapping[str, Any] | None,
                  settings: TrackerSettings, source: str) -> tuple[Tracker, dict[str, Any]]:
    """(tracker, description) for the pipeline ``model`` with metadata ``metadata`` (:func:`read_metadata`).

    The pipeline's own RUL band (``rate_scales``) is the future-eps spread; a pipeline whose metadata carries a
    damage law with a rate scale had it calibrated with s in the law, so that share is removed
    (:func:`~.particle_rul.eps_log_sigmas`). The description (JSON) names the law's source and the band."""
    require_calibrated(model, source)
    damage, where = damage_config(metadata, fallback_damage, source)
    law = DamageLaw.from_config(damage, model, where)
    with_s = where.endswith("metadata") and law.rate_scale_sigma > 0
    eps = eps_log_sigmas(model, law, with_s)
    rul = ParticleRUL(model, law, settings.max_rate_scale, settings.bisections, eps)
    return Tracker(law, rul, settings), {"damage": damage, "damage_source": where,
                                         "rate_scale_sigma": law.rate_scale_sigma,
                                         "eps_log_sigmas": list(eps), "band_included_rate_scale": with_s}
