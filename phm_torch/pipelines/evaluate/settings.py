"""Typed settings of the evaluation pipeline (:func:`~.pipeline.evaluate_rul`).

Each class checks its own values in its constructor, and every error is a ``ValueError`` naming the config
field (``fdi_interval.coverage``, ``rul.n_samples``) and the value, so a bad setting stops the run before any
data is read. The values live in ``conf/evaluate.yaml`` (no defaults here: one home per value).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from ...checks import integer, number
from ...params import ActuatorParams


@dataclass(frozen=True)
class RULSettings:
    """The physics RUL band (``rul``): Monte Carlo runs per vector, bisection steps inside the crossing
    interval, |delta| bound [k units], and the online band (``rate`` or ``initial_state``)."""

    n_samples: int
    refine_iterations: int
    delta_bracket: float
    band: str

    def __post_init__(self) -> None:
        object.__setattr__(self, "n_samples", integer(self.n_samples, "rul.n_samples", 2))
        object.__setattr__(self, "refine_iterations", integer(self.refine_iterations, "rul.refine_iterations", 0))
        object.__setattr__(self, "delta_bracket", number(self.delta_bracket, "rul.delta_bracket", 0.0, strict=True))
        object.__setattr__(self, "band", str(self.band))


@dataclass(frozen=True)
class ReferenceSettings:
    """The physics reference RUL (``reference``): event grid [h] and bisection steps."""

    step_hours: float
    refine_iterations: int

    def __post_init__(self) -> None:
        object.__setattr__(self, "step_hours", number(self.step_hours, "reference.step_hours", 0.0, strict=True))
        object.__setattr__(self, "refine_iterations", integer(self.refine_iterations, "reference.refine_iterations", 0))

    def as_dict(self) -> dict[str, Any]:
        """The cache key's view (the config node's keys and values)."""
        return {"step_hours": self.step_hours, "refine_iterations": self.refine_iterations}


@dataclass(frozen=True)
class CalibrationSettings:
    """How the exported pipeline's uncertainty is calibrated on held-out records.

    Attributes:
        split: the held-out split (``fdi_band.split``), never the evaluated one.
        noise: relative current noise added to its records (``fdi_band.noise``), the first calibrated level.
        correct_median: calibrate eta_50 too (``fdi_band.correct_median``).
        prior_faulty: fault rate P(faulty) is moved to (``verdict.prior_faulty``); None: the split's own.
        coverage: per-parameter coverage of the k_hat intervals (``fdi_interval.coverage``).
        min_count: fewest records per difficulty class (``fdi_interval.min_count``).
        noise_levels: every calibrated noise level: ``noise`` and the increasing ``fdi_interval.noise_levels``.
        consistency_quantile: ``consistency.quantile``.   ood_quantile: ``ood.quantile``.
    """

    split: str
    noise: float
    correct_median: bool
    prior_faulty: float | None
    coverage: float
    min_count: int
    noise_levels: tuple[float, ...]
    consistency_quantile: float
    ood_quantile: float

    @classmethod
    def from_nodes(
        cls,
        fdi_band: Mapping[str, Any],
        verdict: Mapping[str, Any],
        fdi_interval: Mapping[str, Any],
        consistency_quantile: Any,
        ood_quantile: Any,
    ) -> CalibrationSettings:
        """From the config nodes ``fdi_band``, ``verdict``, ``fdi_interval`` and the two quantiles."""
        noise = number(fdi_band["noise"], "fdi_band.noise", 0.0)
        extra = fdi_interval.get("noise_levels") or []
        if not isinstance(extra, Sequence) or isinstance(extra, str):
            raise ValueError(f"fdi_interval.noise_levels must be a list of noise levels, got {extra!r}")
        levels = [noise]
        for i, value in enumerate(extra):
            level = number(value, f"fdi_interval.noise_levels[{i}]", 0.0, strict=True)
            if level <= levels[-1]:
                raise ValueError(
                    f"fdi_interval.noise_levels[{i}] must exceed {levels[-1]!r} (fdi_band.noise and the "
                    f"levels before it, increasing), got {level!r}"
                )
            levels.append(level)
        return cls(
            split=str(fdi_band["split"]),
            noise=noise,
            correct_median=bool(fdi_band["correct_median"]),
            prior_faulty=verdict.get("prior_faulty"),
            coverage=fdi_interval["coverage"],
            min_count=fdi_interval["min_count"],
            noise_levels=tuple(levels),
            consistency_quantile=consistency_quantile,
            ood_quantile=ood_quantile,
        )

    def __post_init__(self) -> None:
        if self.prior_faulty is not None:
            prior = number(self.prior_faulty, "verdict.prior_faulty", 0.0, strict=True)
            if prior >= 1.0:
                raise ValueError(f"verdict.prior_faulty must be in (0, 1), got {prior!r}")
            object.__setattr__(self, "prior_faulty", prior)
        coverage = number(self.coverage, "fdi_interval.coverage", 0.0, strict=True)
        if coverage >= 1.0:
            raise ValueError(f"fdi_interval.coverage must be in (0, 1), got {coverage!r}")
        object.__setattr__(self, "coverage", coverage)
        object.__setattr__(self, "min_count", integer(self.min_count, "fdi_interval.min_count", 1))
        for name in ("consistency_quantile", "ood_quantile"):
            field = name.replace("_", ".", 1)
            object.__setattr__(self, name, number(getattr(self, name), field, 0.0, strict=True))


@dataclass(frozen=True)
class EvaluateSettings:
    """Everything :func:`~.pipeline.evaluate_rul` needs, checked.

    Attributes:
        data_dir: the dataset store.   split: the evaluated split (``rul``).   bundle: the SurrogateBundle file.
        out_dir: where the figures go (the app writes the JSON and the exported files there).
        seed: seeds the Monte Carlo runs and the calibration noise.
        damage: the damage config node (plain), built with the actuator's nominal vector.
        assessment: the assessment config node (plain); None: the one the store was made with.
        rul, reference, calibration: see their classes.   min_present: ``online.min_present``.
        requested_provenance: the ``{"actuator", "command"}`` records the config chose (None where unset);
            ``explicit``: the keys set explicitly (a mismatch with the artefacts is then an error).
        fallback_actuator: the configured actuator, for a store that records none.
    """

    data_dir: str
    split: str
    bundle: str
    out_dir: Path
    seed: int
    damage: Mapping[str, Any]
    assessment: Mapping[str, Any] | None
    rul: RULSettings
    reference: ReferenceSettings
    calibration: CalibrationSettings
    min_present: float
    requested_provenance: Mapping[str, Any]
    explicit: frozenset[str]
    fallback_actuator: ActuatorParams | None

    def __post_init__(self) -> None:
        object.__setattr__(self, "seed", integer(self.seed, "seed"))
        object.__setattr__(self, "min_present", number(self.min_present, "online.min_present", 0.0, True))
        object.__setattr__(self, "out_dir", Path(self.out_dir))
        if self.calibration.split == self.split:
            raise ValueError(
                f"fdi_band.split must differ from split (both {self.split!r}): the FDI band would be "
                "calibrated on the signals it is evaluated on"
            )
