"""What the tracker achieved on simulated histories of the pipeline's own actuator: a companion file beside the
pipeline (``<stem>.tracker_check.json``) that phm-run's companions stage writes and phm-track reads.

A tracker may be right on the reference actuator and wrong on another: on a robust ball screw whose chirp does not
identify what decides its health, the same filter's 5-95 % band held the true RUL on 41 % of the inspections and
flagged every end of life early. Without truth a user cannot see that; so the companions stage tracks its own life
split (truth known) with the files and rule phm-track will use, records the figures here, and phm-track warns once
per run where they fall short (:meth:`TrackerCheck.warnings`), naming the figures. Most of those histories trained
the near-nominal FDI, so the figures lean to optimism: a shortfall here is a floor on the shortfall to expect.
"""

from __future__ import annotations

import os
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

from ..io.atomic import write_json
from .response import check_probe, read_companion_json

FORMAT = "phm_torch.tracker_check/1"
FIGURES = (  # phm_torch.prognostics.life_metrics' figures of the tracker, as recorded
    "coverage_5_95",
    "alpha_lambda",
    "prognostic_horizon",
    "eol_flagged_within_one_inspection",
    "eol_flagged_early",
)
COVERAGE_WARNING = 0.7  # a 5-95 % band holding the true RUL less often than this is announced
EARLY_WARNING = 0.5  # ends of life flagged early more often than this are announced


@dataclass(frozen=True)
class TrackerCheck:
    """The tracker's figures on a life split of the pipeline's actuator.

    Attributes:
        figures: {name in :data:`FIGURES`: value or None (not measurable)}.
        rule: the end-of-life rule they were measured under (``verdict``, ``faulty_at``).
        histories: run-to-failure histories tracked.   inspections: their inspections.
        pipeline: what it was measured for (``probe_k_hat``, ``source``), as an FDI response records it.
        timing_share_off: the share of those (on-time) inspections the timing scan read best 0.3 ms or more away
            (:mod:`.timing_spread`; None: not measured), from which phm-track judges a fleet's timing.
    """

    figures: Mapping[str, float | None]
    rule: Mapping[str, str]
    histories: int
    inspections: int
    pipeline: Mapping[str, Any] = field(default_factory=dict)
    timing_share_off: float | None = None

    def __post_init__(self) -> None:
        unknown = sorted(set(self.figures) - set(FIGURES))
        if unknown:
            raise ValueError(f"tracker check: unknown figures {unknown} (known: {list(FIGURES)})")
        for name, value in self.figures.items():
            if value is not None and not 0.0 <= float(value) <= 1.0:
                raise ValueError(f"tracker check: {name} must be in [0, 1] or null, got {value!r}")
        if self.histories < 1:
            raise ValueError(f"tracker check: histories must be >= 1, got {self.histories}")

    @classmethod
    def from_metrics(
        cls, tracked: Mapping[str, Any], rule: Mapping[str, str], pipeline: Mapping[str, Any]
    ) -> TrackerCheck:
        """From phm-track's metrics of a run with truth (``tracker`` figures, ``actuators``, ``inspections``)."""
        scores = tracked.get("tracker") or {}
        figures = {name: None if scores.get(name) is None else float(scores[name]) for name in FIGURES}
        timing = tracked.get("timing") or {}
        share = None if timing.get("aligned", True) else float(timing["share_off"])  # read on time only
        return cls(figures, dict(rule), int(tracked["actuators"]), int(tracked["inspections"]), dict(pipeline), share)

    def check_for(self, model: Any, source: str) -> None:
        """Raise ValueError unless these figures were measured with the pipeline ``model``."""
        check_probe(self.pipeline, model, source, "tracker check", "measured")

    def warnings(self, rule: Mapping[str, str] | None = None) -> list[str]:
        """One line per figure short of its threshold ([] for none); ``rule``: the one this run uses, said where it
        is not the measured one."""
        where = (
            f"on {self.histories} simulated run-to-failure histories of this actuator ({self.inspections} "
            f"inspections, rule {self.rule.get('verdict')}/{self.rule.get('faulty_at')})"
        )
        lines = []
        coverage, early = self.figures.get("coverage_5_95"), self.figures.get("eol_flagged_early")
        if coverage is not None and coverage < COVERAGE_WARNING:
            lines.append(
                f"{where}, the tracker's 5-95 % RUL band held the true RUL on {100 * coverage:.0f} % of the "
                "inspections: read its bands as narrower than the truth"
            )
        if early is not None and early > EARLY_WARNING:
            lines.append(
                f"{where}, it flagged {100 * early:.0f} % of the ends of life early: expect RULs of 0 well before "
                "the end of life"
            )
        if lines and rule is not None and dict(rule) != {k: self.rule.get(k) for k in rule}:
            lines.append(f"this run's end-of-life rule {dict(rule)} was not the one measured")
        return lines

    def to_json(self) -> dict[str, Any]:
        return {
            "format": FORMAT,
            "pipeline": dict(self.pipeline),
            "rule": dict(self.rule),
            "histories": self.histories,
            "inspections": self.inspections,
            "figures": dict(self.figures),
            "timing_share_off": self.timing_share_off,
        }

    def save(self, path: str | os.PathLike) -> None:
        """Write the check as JSON, atomically."""
        write_json(path, self.to_json())

    @classmethod
    def load(cls, path: str | os.PathLike) -> TrackerCheck:
        """Read a check written by :meth:`save` (JSON only)."""
        data = read_companion_json(path, FORMAT, "tracker check")
        try:
            return cls(
                data["figures"],
                data["rule"],
                int(data["histories"]),
                int(data["inspections"]),
                data["pipeline"],
                data.get("timing_share_off"),  # absent in a check written before 2026-11-30 (night)
            )
        except KeyError as exc:
            raise ValueError(f"tracker check {path}: {exc.args[0]!r} missing") from None
