"""The caveats an exported pipeline's held-out figures put on its answers (its metadata's ``held_out_quality``,
measured by phm-evaluate: :mod:`phm_torch.pipelines.evaluate.quality`).

A verdict is read with the rate at which verdicts of its kind were wrong on held-out records of the same actuator
and command: a "healthy" with the share of faulty records answered healthy, a "faulty" with the share of healthy
ones answered faulty. Where either passes :data:`VERDICT_ERROR_WARNING`, or the full flow's RUL band covered fewer
of the reference RULs than :data:`RUL_COVERAGE_WARNING`, phm-predict and phm-track say so once per run. A wide band
that covers is not warned of: it is honest, and its width is in every answer.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

VERDICT_ERROR_WARNING = 0.10  # a verdict kind wrong on more held-out records than this is announced
RUL_COVERAGE_WARNING = 0.7  # a full-flow RUL band (p5-p95) covering fewer evaluated reference RULs is announced


def held_out(metadata: Mapping[str, Any]) -> dict[str, Any] | None:
    """The pipeline's ``held_out_quality`` (None for a file exported before phm-evaluate measured it)."""
    quality = metadata.get("held_out_quality")
    return dict(quality) if isinstance(quality, Mapping) else None


def verdict_error(quality: Mapping[str, Any] | None, healthy: bool) -> float | None:
    """The held-out rate of wrong verdicts of this kind: faulty records answered healthy for ``healthy``, healthy
    ones answered faulty otherwise; None when not measured."""
    if quality is None:
        return None
    value = quality.get("missed_faulty" if healthy else "false_alarm")
    return None if value is None else float(value)


def quality_warnings(quality: Mapping[str, Any] | None) -> list[str]:
    """One line per caveat of the held-out figures that passes its threshold ([] for none, or none measured)."""
    if quality is None:
        return []
    lines = []
    where = (
        f"on {quality.get('records')} held-out records ({quality.get('split')}) of this actuator and command, drawn "
        "as its training set was (many near the health boundary)"
    )
    for key, said, truth in (("missed_faulty", "healthy", "faulty"), ("false_alarm", "faulty", "healthy")):
        value = quality.get(key)
        if value is not None and value > VERDICT_ERROR_WARNING:
            lines.append(
                f"{where}, the pipeline answered {100 * value:.0f} % of the {truth} ones {said}: read a '{said}' "
                f"verdict with each record's verdict_held_out_error and the k intervals, not alone"
            )
    coverage = quality.get("rul_band_coverage_full_flow")
    if coverage is not None and coverage < RUL_COVERAGE_WARNING:
        lines.append(
            f"the RUL band (p5-p95) covered {100 * coverage:.0f} % of the reference RULs of "
            f"{quality.get('rul_vectors')} evaluated records of this actuator and command: read rul_hours as "
            "narrower than the truth"
        )
    return lines
