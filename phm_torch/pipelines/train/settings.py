"""Typed settings of the training pipeline (:func:`~.pipeline.train_surrogates`).

Each class checks its own values in its constructor, and every error is a ``ValueError`` naming the config
field (``eval.noise``, ``model.fit.patience``) and the value, so a bad setting stops the run before any data
is read. The values live in ``conf/train.yaml`` and ``conf/model/*.yaml`` (no defaults here: one home per
value); :class:`FDIModel` is the ``_target_`` of the ``model`` node.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from ...checks import integer, number
from ...surrogates.classifiers.refinement import BoundaryRefinement
from ...surrogates.fdi_mlp import FDIMLP
from ...surrogates.lightning_fdi import NOISE_INPUT_NEEDS, FDIModule

INPUTS = ("gappy", "full")
ESTIMATORS = ("least_squares", "bayesian")
LOGGERS = ("csv", "tensorboard")
ROLES = ("train", "val")
NETWORK_SIZE = ("n_inputs", "n_hidden", "n_layers", "n_members")  # the top-level settings set them
NETWORK_NOISE = {"default_noise": "eval.noise", "max_noise": "model.augment.noise"}


@dataclass(frozen=True)
class FitSettings:
    """How the FDI network is fitted (``model.fit``).

    Attributes:
        max_epochs: epochs at most (>= 1).  patience: epochs without a better monitored err_k before stopping.
        batch_size: training signals per step; ``None``: the whole set (LM needs it).
        inputs: ``gappy`` (coefficients from the selected samples) or ``full`` (the full projection).
        shifted_copies: how many more copies of the fitting records the network is fitted on, each record read
            moved by its own random shift within +- ``max_shift`` samples of the store's grid (a trigger that is not
            exact; the end-to-end model's ``model.augment.max_shift`` draws one per batch instead). 0: none.
    """

    max_epochs: int
    patience: int
    batch_size: int | None
    inputs: str
    shifted_copies: int = 0
    max_shift: int = 0

    def __post_init__(self) -> None:
        _set(self, "max_epochs", integer(self.max_epochs, "model.fit.max_epochs", 1))
        _set(self, "patience", integer(self.patience, "model.fit.patience", 1))
        _set(self, "shifted_copies", integer(self.shifted_copies, "model.fit.shifted_copies", 0))
        _set(self, "max_shift", integer(self.max_shift, "model.fit.max_shift", 0))
        if self.shifted_copies and not self.max_shift:
            raise ValueError(f"model.fit.shifted_copies={self.shifted_copies} needs model.fit.max_shift >= 1")
        if self.batch_size is not None:
            _set(self, "batch_size", integer(self.batch_size, "model.fit.batch_size", 1))
        if self.inputs not in INPUTS:
            raise ValueError(f"model.fit.inputs must be one of {list(INPUTS)}, got {self.inputs!r}")


class FDIModel:
    """The ``model`` node: the FDI network's Lightning module, the network's own settings and how it is fitted.

    Args:
        fit: ``model.fit`` (:class:`FitSettings` or its mapping).
        network: keyword settings of the FDI network (``input_scaling``, ``noise_input``, ...); its size is the
            top-level ``n_hidden``/``n_layers``/``n_members`` and its noise range ``eval.noise`` and
            ``model.augment.noise``, so none of those may be set here (one home per value).
        end_to_end: the gappy layer inside the model, trained through (``model.end_to_end``).
        **module: the :class:`FDIModule`'s own settings (``optimizer``, ``lr``, ``augment``, ...), passed to it
            as given (its defaults are its own).
    """

    def __init__(
        self, fit: FitSettings | Mapping[str, Any], network: Mapping[str, Any] | None, end_to_end: bool, **module: Any
    ):
        if not isinstance(fit, FitSettings):
            if not isinstance(fit, Mapping):
                raise ValueError(f"model.fit must be a mapping, got {fit!r}")
            known = {f.name for f in dataclasses.fields(FitSettings)}
            unknown = sorted(set(fit) - known)
            if unknown:
                raise ValueError(f"model.fit: unknown setting(s) {unknown}")
            required = ("max_epochs", "patience", "batch_size", "inputs")  # None where missing: named by the check
            optional = {name: fit[name] for name in known - set(required) if name in fit}
            fit = FitSettings(*(fit.get(name) for name in required), **optional)
        network = dict(network or {})
        for key in NETWORK_SIZE:
            if key in network:
                raise ValueError(f"model.network.{key}: set the top-level {key} instead (one home per value)")
        for key, home in NETWORK_NOISE.items():
            if key in network:
                raise ValueError(f"model.network.{key}: it is {home} (one home per value)")
        if end_to_end and fit.shifted_copies:
            raise ValueError(
                "model.fit.shifted_copies is for a network fitted on precomputed inputs; end to end, "
                "model.augment.max_shift reads each batch's records moved"
            )
        augment = module.get("augment")
        self.max_noise = float(augment.noise) if augment is not None else 0.0  # SignalAugment checks it
        if network.get("noise_input") and (not end_to_end or self.max_noise <= 0):
            raise ValueError(NOISE_INPUT_NEEDS)  # before the module: the input scaling needs the range
        self.fit, self.network, self.end_to_end, self.module = fit, network, bool(end_to_end), dict(module)

    @property
    def optimizer(self) -> str | None:
        """``model.optimizer`` as configured (``None``: the module's default)."""
        return self.module.get("optimizer")

    def network_settings(self, eval_noise: float) -> dict[str, Any]:
        """Keyword settings of the FDI network; a noise-aware one (told each record's noise level) is trained on
        levels in [0, ``model.augment.noise``] and assumes ``eval.noise`` when told nothing."""
        out = dict(self.network)
        if out.get("noise_input"):
            out.update(default_noise=min(eval_noise, self.max_noise), max_noise=self.max_noise)
        return out

    def build(self, network: FDIMLP, gappy: Any) -> FDIModule:
        """The Lightning module training ``network`` (with the gappy layer inside when end to end)."""
        return FDIModule(network=network, gappy=gappy if self.end_to_end else None, **self.module)


@dataclass(frozen=True)
class GappySettings:
    """The gappy POD layer (``gappy``): ``estimator`` least_squares (the paper's G alpha = f) or bayesian
    (posterior mean with the training statistics of the truncated modes); ``ridge`` its Tikhonov term (>= 0)."""

    estimator: str
    ridge: float

    def __post_init__(self) -> None:
        _set(self, "ridge", number(self.ridge, "gappy.ridge", 0.0))
        if self.estimator not in ESTIMATORS:
            raise ValueError(f"gappy.estimator must be one of {list(ESTIMATORS)}, got {self.estimator!r}")


@dataclass(frozen=True)
class EvalSettings:
    """Evaluation on the validation split (``eval``): current ``noise`` std as a fraction of each signal's RMS,
    ``missing`` selected samples per signal, the OOD threshold's training ``ood_quantile``, and
    ``latency_repeats`` calls timed for the single-signal latencies."""

    noise: float
    missing: int
    ood_quantile: float
    latency_repeats: int

    def __post_init__(self) -> None:
        _set(self, "noise", number(self.noise, "eval.noise", 0.0))
        _set(self, "missing", integer(self.missing, "eval.missing", 0))
        _set(self, "ood_quantile", number(self.ood_quantile, "eval.ood_quantile", 0.0))
        _set(self, "latency_repeats", integer(self.latency_repeats, "eval.latency_repeats", 1))


@dataclass(frozen=True)
class TrainSettings:
    """Everything the training pipeline reads besides the injected strategies (selector, classifier).

    Attributes:
        data_dir: the dataset store (phm-generate).  out_dir: checkpoints, logs and the refinement's labels.
        splits: role (``train``, ``val``) -> split name in the store.  limits: role -> rows read at most (None: all).
        seed: seeds weight initialisation, shuffling, the robustness corruption and every derived stream.
        n_modes, n_points, n_hidden, n_layers, n_members: POD modes, selected samples, the FDI network's size.
        model: the ``model`` node.  pod_solver: the POD's SVD solver.  gappy, eval: their nodes.
        monitor_fraction: training signals held out to choose the FDI epoch (in [0, 0.5)).
        max_missed_fault_rate: ``calibration.max_missed_fault_rate`` (None: the classifiers' own thresholds).
        verdict_max_missed_fault_rate: ``calibration.verdict_max_missed_fault_rate``: None, or the verdict classifier
            is fitted on the FDI's fitting rows and its threshold raised until at most this fraction of the faulty
            monitor rows' estimates (held out from the FDI's fit) score healthy.
        classifier_labels: also fit the health classifier on the store's assessment-only labels split.
        refine: the classifier's boundary refinement; refine_device: its simulator device.
        damage: the damage law's config node (``_target_`` and values), whose paths the refinement's path labels
            lie on (None: no paths).
        verdict_classifier: also fit the verdict classifier on the estimates.  forward_check: the forward surrogate.
        loggers: Lightning loggers by name.  trainer: Lightning Trainer keyword settings.
        ckpt_path: resume the FDI training from this checkpoint (None: from scratch).
        requested_provenance: ``{"actuator", "command"}`` records the config asks for (None where it asks none).
        explicit_provenance: the keys the user chose (``actuator=<name>``), which the store must match.
        drive_range: the drive's current range, this multiple of the actuator's ``current_limit`` (None: none):
            records beyond it calibrate no out-of-distribution threshold, and the exported pipeline calls them
            ``overcurrent``; see ``conf/train.yaml``.  fit_within_drive_range: also leave them out of every fit.
    """

    data_dir: str
    out_dir: Path
    splits: Mapping[str, str]
    limits: Mapping[str, int | None]
    seed: int
    n_modes: int
    n_points: int
    n_hidden: int
    n_layers: int
    n_members: int
    model: FDIModel
    pod_solver: str
    gappy: GappySettings
    eval: EvalSettings
    monitor_fraction: float
    max_missed_fault_rate: float | None
    classifier_labels: bool
    refine: BoundaryRefinement
    refine_device: str
    verdict_classifier: bool
    forward_check: bool
    loggers: tuple[str, ...]
    trainer: Mapping[str, Any]
    ckpt_path: str | None
    requested_provenance: Mapping[str, Any]
    explicit_provenance: frozenset[str]
    drive_range: float | None = None
    fit_within_drive_range: bool = False
    damage: Mapping[str, Any] | None = None
    verdict_max_missed_fault_rate: float | None = None

    def __post_init__(self) -> None:
        _set(self, "seed", integer(self.seed, "seed", 0))
        for name in ("n_modes", "n_points", "n_hidden", "n_layers", "n_members"):
            _set(self, name, integer(getattr(self, name), name, 1))
        if self.n_members > 1 and self.model.optimizer == "lm":
            raise ValueError(
                f"n_members={self.n_members} needs model=fdi_adam or model=fdi_e2e (LM trains one network)"
            )
        if self.n_points < self.n_modes and self.gappy.ridge == 0.0 and self.gappy.estimator == "least_squares":
            raise ValueError(
                f"n_points={self.n_points} < n_modes={self.n_modes}: the gappy system is "
                f"underdetermined (choose n_points >= n_modes, gappy.ridge > 0 or gappy.estimator=bayesian)"
            )
        if self.max_missed_fault_rate is not None:
            _set(
                self,
                "max_missed_fault_rate",
                number(self.max_missed_fault_rate, "calibration.max_missed_fault_rate", 0.0),
            )
        rate = self.verdict_max_missed_fault_rate
        if rate is not None:
            rate = number(rate, "calibration.verdict_max_missed_fault_rate", 0.0)
            if rate >= 1.0:
                raise ValueError(f"calibration.verdict_max_missed_fault_rate must be in [0, 1), got {rate!r}")
            if not self.verdict_classifier:
                raise ValueError(
                    "calibration.verdict_max_missed_fault_rate calibrates the verdict classifier: set "
                    "verdict_classifier=true, or leave the rate null"
                )
            if self.monitor_fraction == 0:
                raise ValueError(
                    "calibration.verdict_max_missed_fault_rate is calibrated on the training signals held out from "
                    "the FDI's fit: set monitor_fraction > 0"
                )
            _set(self, "verdict_max_missed_fault_rate", rate)
        if self.drive_range is not None:
            _set(self, "drive_range", number(self.drive_range, "drive_range", 1.0))
        fraction = number(self.monitor_fraction, "monitor_fraction", 0.0)
        if fraction >= 0.5:
            raise ValueError(f"monitor_fraction must be < 0.5 (a fraction of the training signals), got {fraction!r}")
        _set(self, "monitor_fraction", fraction)
        if not isinstance(self.loggers, (list, tuple)) or any(n not in LOGGERS for n in self.loggers):
            raise ValueError(f"loggers must be a list drawn from {list(LOGGERS)}, got {self.loggers!r}")
        _set(self, "loggers", tuple(self.loggers))
        if set(self.splits) != set(ROLES):
            raise ValueError(f"splits must map exactly the roles train and val to split names, got {dict(self.splits)}")
        _set(
            self,
            "limits",
            {role: None if rows is None else integer(rows, f"limit.{role}", 1) for role, rows in self.limits.items()},
        )


def _set(settings: Any, name: str, value: Any) -> None:
    """Store a checked value (an int or float as such) on a frozen settings object."""
    object.__setattr__(settings, name, value)
