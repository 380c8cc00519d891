"""What a workbench run returns: its ranking rounds and everything the report shows (:mod:`.report`)."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

from .calibrate import Calibration
from .candidates import Candidate
from .closure import ClosureResult
from .data import Record
from .settings import WorkbenchSettings


@dataclass
class Round:
    """One ranking round: the model tested and its candidates (best first)."""

    model: Calibration
    candidates: list[Candidate]
    added: str | None = None
    added_model: Calibration | None = None


@dataclass
class WorkbenchResult:
    """Everything the report shows (see :mod:`phm_torch.workbench.report`)."""

    records: list[Record]
    model: Calibration
    final: Calibration
    rounds: list[Round]
    before_after: list[Calibration]
    closure: ClosureResult | None
    diagnostics: dict[str, dict]
    metrics: dict[str, dict]
    noise: list[dict[str, float]]
    timing: dict[str, float]
    settings: WorkbenchSettings
    fidelity: str
    actuator: str = "unnamed"
    orders: dict[str, Any] = field(default_factory=dict)
    fidelity_gap: dict[str, Any] | None = None  # the LF model against HF on the records (fidelity_gap.py)
    bench_lines: dict[str, list[dict[str, Any]]] = field(default_factory=dict)  # removed per record (bench_lines.py)

    @property
    def candidates(self) -> list[Candidate]:
        """Candidates of the first round (against the configured model), best first."""
        return self.rounds[0].candidates if self.rounds else []

    @property
    def added(self) -> list[str]:
        return [r.added for r in self.rounds if r.added]
