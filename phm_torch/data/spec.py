"""The settings of a dataset store (``conf/dataset/*.yaml``): split sizes, chunking, signal fidelity, the
healthy-fraction calibration of the importance sampler and the effects of the records.

``DatasetSpec`` is the ``_target_`` of the ``dataset`` node (``phm_torch.data.generation.DatasetSpec``,
the path the configs and the store fingerprints carry).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

from ..effects import build_effects
from ..physics.motor import MOTORS
from . import randomization
from .life import LifeSpec

SPLITS = ("nominal", "train", "val", "rul")  # the signal splits (the optional labels split: labels.py)


@dataclass(frozen=True)
class DatasetSpec:
    """What to generate.

    Attributes:
        n_train, n_val: rows of the importance-sampled splits (full domain).
        n_rul: rows of the RUL split, importance-sampled on the restricted domain of normalised
            L-infinity radius ``rul_radius`` about nominal (mostly healthy actuators).
        uniform: 0-based fault indices left uniform by the sampling (k7, eccentricity phase -> 6).
        chunk_size: rows per chunk = simulator batch size.
        fidelity: model producing the signals (``hf``; ``lf`` for quick tests).
        compile: compile the signal simulator (pays ~15-30 s once per process).
        substeps: simulator substeps per control period (null: the fidelity's default).
        n_labels: rows of the assessment-only ``labels`` split (K, healthy, margins; no signals),
            importance-sampled on the full domain like train, with their own seed stream; 0 = none.
        label_chunk_size: the most rows per labels chunk = assessment batch (memory ~0.3 MB per row
            with the default sweep); the rows are spread evenly over ceil(n_labels / label_chunk_size)
            chunks.
        effects: physical effects of the library added to the signal simulator, ``{name: {param: value}}``
            (``{}`` = the effect's defaults): train the surrogates on the physics a bench turned out to
            have (``phm-workbench`` names it). The assessment function, hence the health labels, is
            unchanged: health stays a property of the fault vector.
        randomize: effect parameters drawn per ``train`` record, ``{name: {param: [low, high]}}`` (uniform;
            domain randomisation, :mod:`phm_torch.data.randomization`); the other splits keep ``effects``.
        healthy_fraction: the healthy fraction the full-domain splits (train, val, labels) are sampled
            for: the importance sampler's distance exponent is calibrated on a pilot of assessment labels
            (:mod:`phm_torch.data.calibration`); null = the paper's scaling, no pilot.
        healthy_fraction_tolerance: the paper's scaling is kept when the pilot is within this of the target.
        near_nominal_share: where the calibration moves the samples away from nominal (exponent > 1: a robust
            actuator), this share of the radial law stays the paper's, a floor under the density near nominal
            (:mod:`phm_torch.data.calibration`, step 6); 0 (the default) = none. It trades boundary records for
            near-nominal ones: at the paper's scale the second actuator's verdict missed twice the faults with
            0.25 (docs/dataset.md), so it is a choice for a small store read mostly near nominal, not a default.
        pilot_size: fault vectors of the calibration pilot (assessed in batches of ``chunk_size``).
        life: the run-to-failure ``life`` split (:class:`~phm_torch.data.life.LifeSpec`, or a mapping of its
            fields); ``n_actuators`` 0 (the default) = none. Not part of the store's fingerprint: a life split
            can be added to a finished store.
    """

    n_train: int
    n_val: int
    n_rul: int
    rul_radius: float
    uniform: tuple[int, ...]
    chunk_size: int
    fidelity: str
    compile: bool
    substeps: int | None = field(default=None)
    n_labels: int = 0
    label_chunk_size: int = 4096
    effects: Mapping[str, Mapping[str, Any] | None] = field(default_factory=dict)
    randomize: Mapping[str, Mapping[str, Sequence[float]]] = field(default_factory=dict)
    randomized: tuple[randomization.RandomizedParam, ...] = field(init=False, repr=False, default=())
    healthy_fraction: float | None = 0.3
    healthy_fraction_tolerance: float = 0.05
    near_nominal_share: float = 0.0
    pilot_size: int = 1536
    life: LifeSpec | Mapping[str, Any] | None = None

    def __post_init__(self) -> None:
        object.__setattr__(self, "uniform", tuple(int(i) for i in self.uniform))
        if not isinstance(self.effects, Mapping):
            raise ValueError(f"dataset.effects must map effect names to their parameters, got {self.effects!r}")
        effects = {str(name): dict(values or {}) for name, values in self.effects.items()}
        try:
            build_effects(effects)
        except ValueError as e:
            raise ValueError(f"dataset.{e}") from None
        object.__setattr__(self, "effects", effects)
        object.__setattr__(self, "randomized", randomization.parse_randomization(self.randomize, effects))
        object.__setattr__(self, "life", LifeSpec.of(self.life))
        for name, low in (
            ("n_train", 1),
            ("n_val", 0),
            ("n_rul", 0),
            ("chunk_size", 1),
            ("n_labels", 0),
            ("label_chunk_size", 1),
            ("pilot_size", 16),
        ):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int) or v < low:
                raise ValueError(f"dataset.{name} must be an integer >= {low}, got {v!r}")
        if not (isinstance(self.rul_radius, (int, float)) and 0 < self.rul_radius <= 1):
            raise ValueError(f"dataset.rul_radius must be in (0, 1], got {self.rul_radius!r}")
        if self.fidelity not in MOTORS:
            raise ValueError(f"dataset.fidelity must be one of {sorted(MOTORS)}, got {self.fidelity!r}")
        if self.substeps is not None and (not isinstance(self.substeps, int) or self.substeps < 1):
            raise ValueError(f"dataset.substeps must be null or an integer >= 1, got {self.substeps!r}")
        h, tol = self.healthy_fraction, self.healthy_fraction_tolerance
        if h is not None and (isinstance(h, bool) or not isinstance(h, (int, float)) or not 0.0 < h < 1.0):
            raise ValueError(f"dataset.healthy_fraction must be in (0, 1) or null, got {h!r}")
        if isinstance(tol, bool) or not isinstance(tol, (int, float)) or not 0.0 <= tol < 1.0:
            raise ValueError(f"dataset.healthy_fraction_tolerance must be in [0, 1), got {tol!r}")
        share = self.near_nominal_share
        if isinstance(share, bool) or not isinstance(share, (int, float)) or not 0.0 <= share < 1.0:
            raise ValueError(f"dataset.near_nominal_share must be in [0, 1), got {share!r}")

    @property
    def counts(self) -> dict[str, int]:
        """Rows of the signal splits (``SPLITS``)."""
        return {"nominal": 1, "train": self.n_train, "val": self.n_val, "rul": self.n_rul}
