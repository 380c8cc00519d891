"""The test signals of the frequency-response measurement (``assessment.sweep``): frequencies, amplitude, cycles,
settling, refinement and rest angles; frequency_response.py measures the loop with them."""

from __future__ import annotations

import dataclasses
import itertools
import math
from dataclasses import dataclass, field

from ..params import ActuatorParams
from .design import AUTO, SweepDesign
from .margins import NO_RESPONSE_DB


@dataclass(frozen=True)
class SineSweep:
    """The test signals of the frequency-response measurement.

    Attributes:
        frequencies: test frequencies [Hz], increasing; each is snapped so that ``measure_cycles``
            cycles span a whole number of control periods (no spectral leakage). ``"auto"``: derived from
            the actuator's linearised loop by ``design`` (:meth:`resolve`).
        amplitude: command amplitude [rad, user side], the same at every frequency; ``"auto"``: derived
            from the actuator's friction, play, stroke and limits by ``design``.
        cycles: cycles simulated per frequency (from rest), the last ``measure_cycles`` measured.
        measure_cycles: cycles in the Fourier window.
        min_duration: shortest simulation [s] (lets the closed-loop transient decay at high frequency).
        substeps: LF substeps per control period.
        group_size: frequencies simulated together in one batch.
        compile: fuse the simulator substep with ``torch.compile`` (worth it for batches >~ 256).
        design: how the ``"auto"`` values are derived (:class:`~phm_torch.assessment.design.SweepDesign`).
        tolerance: largest relative change of L and T between the last two measurement windows of a settled
            response [-].
        max_extensions: how many times an unsettled response is simulated on to twice the time (0: never).
        refine: rounds of measurement at each vector's interpolated crossings (0: the grid only).
        rotor_positions: the loop is measured with the rotor resting at this many electrical angles 0, 60, 120,
            ... deg (one commutation sector apart) and each vector labelled by its worst (3, the shipped config:
            each phase out of conduction once; 1: at 0 only, which cannot see a short in the phase out of
            conduction there, every store labelled before 2026-11-29 and what an unrecorded value means,
            ``assessment_record.SWEEP_DEFAULTS``; at most 6).
        no_response_db: an open-loop reading |L| below this [dB] is no response (the output stuck in dry friction,
            its phase noise): the phase crossover is sought only below the first such frequency, and a loop whose
            phase has not reached -180 deg there gets the gain margin -|L| [dB] of its last responding reading, a
            lower bound (:func:`~phm_torch.assessment.margins.margins`). None: every reading counts, and a stuck
            reading could make a vector with a 10 dB gain margin "unmeasurable", so faulty (a ball screw's damage
            paths turned faulty and healthy again on 19 of 40 histories; docs/dataset.md).
    """

    frequencies: tuple[float, ...] | str
    amplitude: float | str
    cycles: int
    measure_cycles: int
    min_duration: float
    substeps: int
    group_size: int
    compile: bool
    design: SweepDesign = field(default_factory=SweepDesign)
    tolerance: float = 0.005
    max_extensions: int = 0
    refine: int = 0
    rotor_positions: int = 1
    no_response_db: float | None = NO_RESPONSE_DB

    def __post_init__(self) -> None:
        if self.no_response_db is not None and not (
            math.isfinite(float(self.no_response_db)) and float(self.no_response_db) < 0.0
        ):
            raise ValueError(
                f"assessment.sweep.no_response_db must be a negative level [dB] or null, got {self.no_response_db!r}"
            )
        if isinstance(self.frequencies, str):
            if self.frequencies != AUTO:
                raise ValueError(
                    f"assessment.sweep.frequencies must be a list of frequencies [Hz] or "
                    f"'{AUTO}', got {self.frequencies!r}"
                )
        else:
            try:
                freqs = tuple(float(f) for f in self.frequencies)
            except (TypeError, ValueError):
                raise ValueError(
                    f"assessment.sweep.frequencies must be a list of frequencies [Hz] or "
                    f"'{AUTO}', got {self.frequencies!r}"
                ) from None
            object.__setattr__(self, "frequencies", freqs)
            if len(freqs) < 2:
                raise ValueError(f"assessment.sweep.frequencies needs at least 2 values, got {list(freqs)}")
            if any(not math.isfinite(f) or f <= 0 for f in freqs) or any(b <= a for a, b in itertools.pairwise(freqs)):
                raise ValueError(f"assessment.sweep.frequencies must be positive and increasing, got {list(freqs)}")
        if isinstance(self.amplitude, str):
            if self.amplitude != AUTO:
                raise ValueError(
                    f"assessment.sweep.amplitude must be a number [rad] or '{AUTO}', got {self.amplitude!r}"
                )
        elif (
            isinstance(self.amplitude, bool)
            or not isinstance(self.amplitude, (int, float))
            or not (math.isfinite(self.amplitude) and self.amplitude > 0)
        ):
            raise ValueError(f"assessment.sweep.amplitude must be > 0 [rad], got {self.amplitude}")
        if not isinstance(self.design, SweepDesign):
            raise ValueError(f"assessment.sweep.design must be a SweepDesign, got {self.design!r}")
        if int(self.measure_cycles) != self.measure_cycles or self.measure_cycles < 1:
            raise ValueError(f"assessment.sweep.measure_cycles must be an integer >= 1, got {self.measure_cycles}")
        if int(self.cycles) != self.cycles or self.cycles <= self.measure_cycles:
            raise ValueError(
                f"assessment.sweep.cycles must be an integer > measure_cycles "
                f"({self.measure_cycles}), got {self.cycles}"
            )
        if not (math.isfinite(self.min_duration) and self.min_duration >= 0):
            raise ValueError(f"assessment.sweep.min_duration must be >= 0 [s], got {self.min_duration}")
        if int(self.substeps) != self.substeps or self.substeps < 1:
            raise ValueError(f"assessment.sweep.substeps must be an integer >= 1, got {self.substeps}")
        if int(self.group_size) != self.group_size or self.group_size < 1:
            raise ValueError(f"assessment.sweep.group_size must be an integer >= 1, got {self.group_size}")
        if isinstance(self.tolerance, bool) or not (
            isinstance(self.tolerance, (int, float)) and math.isfinite(self.tolerance) and self.tolerance > 0
        ):
            raise ValueError(f"assessment.sweep.tolerance must be > 0, got {self.tolerance!r}")
        for name, low, high in (("max_extensions", 0, math.inf), ("refine", 0, math.inf), ("rotor_positions", 1, 6)):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int) or not low <= v <= high:
                bound = f">= {low}" if high == math.inf else f"in [{low}, {high}]"
                raise ValueError(f"assessment.sweep.{name} must be an integer {bound}, got {v!r}")

    @property
    def is_resolved(self) -> bool:
        """Both the frequencies and the amplitude are numbers (no ``"auto"``)."""
        return not isinstance(self.frequencies, str) and not isinstance(self.amplitude, str)

    def resolve(self, params: ActuatorParams) -> SineSweep:
        """This sweep with ``"auto"`` frequencies and amplitude derived for ``params`` (explicit values win)."""
        if self.is_resolved:
            return self
        explicit_amp = None if isinstance(self.amplitude, str) else float(self.amplitude)
        if isinstance(self.frequencies, str):
            freqs = self.design.frequencies(params, amplitude=explicit_amp)
        else:
            freqs = self.frequencies
        amp = self.design.amplitude(params, freqs[-1]) if isinstance(self.amplitude, str) else self.amplitude
        return dataclasses.replace(self, frequencies=freqs, amplitude=amp)
