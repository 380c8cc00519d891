"""The assessment function phi_a(k): is the actuator still meeting its control requirements?

ema_reference.md §4: measured on the LF model's frequency response, "healthy" when the phase margin
and the gain margin reach their minima and the closed-loop -3 dB bandwidth is at least a set fraction
of the nominal actuator's (measured the same way, so that the measurement's own bias cancels).
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass
from typing import Any

import torch

from ..faults import FAULT_NAMES, as_fault_tensor
from ..params import ActuatorParams
from ..provenance import actuator_values, digest
from .frequency_response import FrequencyResponse, padded_size, padding_index
from .margins import Margins
from .sweep import SineSweep

log = logging.getLogger(__name__)

# The nominal margins and the invisible faults depend only on the actuator's values, the resolved sweep and the
# device, and are measured uncompiled: one measurement serves every assessment function built alike in a process
# (a generate run builds several: the sampling pilot's, the labels', the records'; a phm-run more).
_MEASURED: dict[tuple[str, str, str], dict[str, Any]] = {}


@dataclass(frozen=True)
class HealthRequirements:
    """Requirement thresholds.

    Attributes:
        phase_margin_deg: minimum phase margin [deg].
        gain_margin_db: minimum gain margin [dB].
        bandwidth_fraction: minimum closed-loop bandwidth as a fraction of the nominal one [-].
    """

    phase_margin_deg: float
    gain_margin_db: float
    bandwidth_fraction: float

    def __post_init__(self) -> None:
        for name in ("phase_margin_deg", "gain_margin_db", "bandwidth_fraction"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
                raise ValueError(f"assessment.requirements.{name} must be a finite number, got {value!r}")
        if not 0.0 <= self.phase_margin_deg < 180.0:
            raise ValueError(
                f"assessment.requirements.phase_margin_deg must be in [0, 180), got {self.phase_margin_deg}"
            )
        if self.gain_margin_db < 0:
            raise ValueError(f"assessment.requirements.gain_margin_db must be >= 0, got {self.gain_margin_db}")
        if not 0.0 < self.bandwidth_fraction <= 1.0:
            raise ValueError(
                f"assessment.requirements.bandwidth_fraction must be in (0, 1], got {self.bandwidth_fraction}"
            )

    def healthy(self, m: Margins, nominal_bandwidth_hz: float) -> torch.Tensor:
        """(B,) bool: every requirement met (a nan margin, i.e. not measurable, fails)."""
        return (
            (m.phase_margin_deg >= self.phase_margin_deg)
            & (m.gain_margin_db >= self.gain_margin_db)
            & (m.bandwidth_hz >= self.bandwidth_fraction * nominal_bandwidth_hz)
        )


@dataclass
class Assessment:
    """phi_a of a batch: ``healthy`` (B,) bool, the measured ``margins`` and ``uncertain`` (B,) bool: the label read
    from the window before the last differs (a reading that has not settled, or never becomes periodic, decides it;
    ``None`` where not known)."""

    healthy: torch.Tensor
    margins: Margins
    uncertain: torch.Tensor | None = None


def reads_as(rows: torch.Tensor, reference: torch.Tensor, rtol: float = 1e-9) -> torch.Tensor:
    """(B,) bool: each row of stacked margins (B, 5) equals ``reference`` (5,) or (1, 5) to ``rtol`` (of at least 1):
    the same reading, e.g. a fault the labels cannot see (a nan, unmeasurable, never equals)."""
    return ((rows - reference).abs() <= rtol * reference.abs().clamp(min=1.0)).all(-1)


def worst_margins(readings: list[Margins]) -> Margins:
    """Every margin's smallest over the readings of the same vectors at several rotor positions (a nan, not
    measurable at one of them, stays nan): the requirements hold at every position exactly when they hold here."""
    if len(readings) == 1:
        return readings[0]
    stacked = torch.stack([m.stacked() for m in readings])  # (P, B, 5)
    worst = torch.where(stacked.isnan().any(0), torch.nan, stacked.amin(0))
    return Margins.from_stacked(worst)


class AssessmentFunction:
    """phi_a(k) from the LF model's measured frequency response.

    Args:
        params: actuator datasheet.
        sweep: test signals (frequencies, amplitude, ...); ``"auto"`` values are derived for ``params``
            (:class:`~phm_torch.assessment.design.SweepDesign`), ``self.sweep`` is the resolved sweep.
        requirements: thresholds.
        device: simulation device.

    The nominal bandwidth is measured on first use, with an uncompiled batch of one, once per process for the
    same actuator values, resolved sweep and device (every assessment function built alike shares it).
    """

    def __init__(
        self,
        params: ActuatorParams,
        sweep: SineSweep,
        requirements: HealthRequirements,
        device: str | torch.device = "cpu",
    ):
        self.params = params
        self.sweep = sweep.resolve(params)
        self.auto = {name: isinstance(getattr(sweep, name), str) for name in ("frequencies", "amplitude")}
        self.requirements = requirements
        # one per rotor position (SineSweep.rotor_positions), one commutation sector (60 electrical deg) apart
        self.response = FrequencyResponse(params, self.sweep, device)
        self.responses = [self.response] + [
            FrequencyResponse(params, self.sweep, device, rotor_angle=j * math.pi / 3, simulator=self.response.sim)
            for j in range(1, self.sweep.rotor_positions)
        ]
        self._nominal: Margins | None = None
        self._invisible: list[str] | None = None
        # this process's measurements of the same actuator, sweep and device (``_MEASURED``)
        sweep_values = sorted((k, v) for k, v in vars(self.sweep).items() if k != "compile")
        key = (digest(actuator_values(params)), repr(sweep_values), str(self.response.device))
        self._shared = _MEASURED.setdefault(key, {})
        self.wall_s = 0.0  # time spent simulating [s]
        self.vectors = 0  # fault vectors assessed
        self.uncertain = 0  # labels that the window before the last reads otherwise

    @property
    def nominal(self) -> Margins:
        """Margins of the nominal actuator (batch of one)."""
        if self._nominal is None and "nominal" in self._shared:
            self._nominal = Margins.from_stacked(self._shared["nominal"].clone())
        if self._nominal is None:
            eager = FrequencyResponse(
                self.params, SineSweep(**{**vars(self.sweep), "compile": False}), self.response.device
            )
            k0 = torch.tensor([self.params.nominal_faults], dtype=torch.float64)
            r = eager.read(k0)
            self._nominal = eager.margins_of(r)
            self._shared["nominal"] = self._nominal.stacked().clone()
        return self._nominal

    @property
    def nominal_bandwidth_hz(self) -> float:
        bw = float(self.nominal.bandwidth_hz[0])
        if not math.isfinite(bw):
            f = self.sweep.frequencies
            raise ValueError(
                f"assessment.sweep.frequencies: the nominal bandwidth is not on the grid "
                f"[{f[0]}, {f[-1]}] Hz (got {bw}); extend the grid"
            )
        return bw

    def record(self) -> dict[str, Any]:
        """JSON-able account of the sweep actually used: frequencies [Hz], amplitude [rad], which of them
        were derived (``auto``), the derivation (linear loop figures, amplitude bounds) when any was, and
        the nominal actuator's measured margins."""
        out: dict[str, Any] = {
            "frequencies": list(self.sweep.frequencies),
            "amplitude": self.sweep.amplitude,
            "auto": dict(self.auto),
        }
        if any(self.auto.values()):
            out["design"] = self.sweep.design.record(self.params)
        out["nominal_margins"] = {k: round(float(v[0]), 4) for k, v in self.nominal.as_dict().items()}
        out["rotor_positions"] = self.sweep.rotor_positions
        out["invisible_faults"] = self.invisible_faults()
        return out

    def invisible_faults(self) -> list[str]:
        """The phase shorts (k3-k5 at 1, one at a time) whose label readings are exactly the nominal actuator's:
        faults the labels cannot see, because the sweep keeps the rotor in one commutation sector where that phase
        does not conduct (``sweep.rotor_positions`` = 3 reads every phase). Measured once, uncompiled (cached)."""
        if self._invisible is None and "invisible" in self._shared:
            self._invisible = list(self._shared["invisible"])
        if self._invisible is None:
            eager = [
                FrequencyResponse(
                    self.params, SineSweep(**{**vars(self.sweep), "compile": False}), r.device, r.rotor_angle
                )
                for r in self.responses
            ]
            k = torch.tensor([self.params.nominal_faults] * 4, dtype=torch.float64)
            k[1:, 2:5] += torch.eye(3, dtype=torch.float64) * (1.0 - k[1:, 2:5])
            found = worst_margins([e.margins_of(e.read(k)) for e in eager]).stacked()
            same = reads_as(found[1:], found[:1])
            self._invisible = [FAULT_NAMES[2 + i] for i in range(3) if bool(same[i])]
            self._shared["invisible"] = list(self._invisible)
        return list(self._invisible)

    def settling(self) -> dict[str, int]:
        """Over every call so far: responses simulated again because they had not settled (``extended``), those
        still moving after ``max_extensions`` (``unsettled``: labelled from their last reading; with
        ``max_extensions`` 0 every reading that moved by more than ``tolerance``), the fault vectors assessed
        (``vectors``) and those whose label the window before the last reads otherwise (``uncertain_labels``)."""
        return {
            "extended": sum(r.extensions for r in self.responses),
            "unsettled": sum(r.unsettled for r in self.responses),
            "vectors": self.vectors,
            "uncertain_labels": self.uncertain,
        }

    def _read(self, response: FrequencyResponse, k: torch.Tensor, batch: int = 0) -> tuple[Margins, Margins]:
        """Margins of k (B, 8) at one rotor position over the last window and the window before. ``batch`` > 0: k
        is a subset of rows of a batch that size, which a compiled simulator reads padded (``padded_size``, at
        most ``batch``; the last row repeated) so that a few compiled batch sizes serve every call, the positions
        sharing one simulator and so its compiled graphs."""
        n = k.shape[0]
        if batch and self.sweep.compile:  # never past the whole batch's size, compiled at the first position
            k = k[padding_index(n, min(padded_size(n), batch), k.device)]
        r = response.read(k)
        return tuple(  # type: ignore[return-value]
            response.margins_of(x).take_rows(slice(0, n)) for x in (r, r.before)
        )

    def __call__(self, faults: torch.Tensor) -> Assessment:
        """Assess (B, 8) fault vectors."""
        k = as_fault_tensor(faults, torch.float64, self.response.device)
        bw0 = self.nominal_bandwidth_hz
        t0 = time.perf_counter()
        unsettled = self.settling()["unsettled"]
        m, m_before = self._read(self.responses[0], k)
        for response in self.responses[1:]:
            # a vector failing at every position read so far, in both windows, is faulty whatever the others read:
            # only the rest are read again (the labels and `uncertain` are those of reading every position; at
            # three positions 1.73x the cost of one on the paper's importance-sampled batch, not 3x: bench_generate)
            rows = torch.nonzero(self.requirements.healthy(m, bw0) | self.requirements.healthy(m_before, bw0))[:, 0]
            if rows.numel() == 0:
                break
            last, before = self._read(response, k[rows], batch=k.shape[0])
            m, m_before = (
                a.put_rows(rows, worst_margins([a.take_rows(rows), b])) for a, b in ((m, last), (m_before, before))
            )
        healthy = self.requirements.healthy(m, bw0)
        uncertain = healthy != self.requirements.healthy(m_before, bw0)
        now_unsettled = self.settling()["unsettled"]
        if self.sweep.max_extensions and now_unsettled > unsettled:  # counted (settling()); apps sum up
            log.debug(
                "assessment: %d responses of %d vectors still changed by more than %g after %d extensions "
                "(assessment.sweep.tolerance / max_extensions); labelled from their last reading",
                now_unsettled - unsettled,
                k.shape[0],
                self.sweep.tolerance,
                self.sweep.max_extensions,
            )
        self.wall_s += time.perf_counter() - t0
        self.vectors += k.shape[0]
        self.uncertain += int(uncertain.sum())
        return Assessment(healthy, m, uncertain)
