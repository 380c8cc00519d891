"""The trained surrogates as one object: what the online pipeline (and its export) loads.

``SurrogateBundle`` holds the POD basis, the selected sample indices (as a :class:`GappyPOD` layer), the
FDI network and the health classifier, and answers the online questions:

* ``bundle.compress(signals (B, n_e)) -> samples (B, n_w)``: keep the selected samples of full records;
* ``bundle.coefficients(samples, mask=None) -> (alpha (B, n_m), residual (B,) [A])``: gappy POD;
* ``bundle.fdi(samples, mask=None, noise=None) -> k_hat (B, 8)`` in [0, 1]: the fault vector (also ``forward``;
  ``noise`` (B,), the records' relative noise, for a noise-aware network);
* ``bundle.estimate(signals (B, n_e), noise=None) -> k_hat (B, 8)`` float64: the FDI on full records as the
  online pipeline runs it (the selected samples, the network told each record's estimated noise level);
* ``bundle.diagnose(samples, mask=None) -> dict``: k_hat, alpha, residual and the ``out_of_distribution``
  flag (residual above ``residual_threshold``);
* ``bundle.health_score(k (B, 8)) -> f (B,)`` float64: **positive = healthy**, negative = faulty, zero on
  the learned boundary (the classifier's score minus its calibrated ``threshold``); smooth in k (RUL
  stopping event); ``bundle.is_healthy(k)`` is f > 0;
* ``bundle.verdict_score(k_hat (B, 8)) -> g (B,)``: the same for an FDI *estimate*, from the verdict
  classifier fitted on estimates (:mod:`.verdict_classifier`) when the bundle has one, else f;
  ``bundle.verdict_healthy(k_hat)`` is g > 0.

Samples are the raw measured current [A] at ``bundle.sample_times`` [s] (indices ``bundle.indices``
into the 20 kHz record of n_e samples); NaN marks a missing sample.

The file format (``save``/``load``) and the rebuilding of the parts are in :mod:`.bundle_file`.
"""

from __future__ import annotations

import os
from collections.abc import Mapping
from pathlib import Path
from typing import Any, ClassVar

import torch
from torch import nn

from .. import __version__
from ..faults import FAULT_NAMES
from .augment import noise_level
from .bundle_file import _prefixed, _spec, read_bundle_file, rebuild_parts, write_bundle_file
from .classifiers import HealthClassifier
from .fdi_ensemble import FDIEnsemble
from .fdi_mlp import FDIMLP
from .forward import ForwardSurrogate
from .full_signal_check import DEFAULT_PLATEAU_THRESHOLD, DEFAULT_ROUGHNESS_THRESHOLD, FullSignalCheck
from .gappy_pod import GappyPOD
from .pod import POD

HEALTH_CONVENTION = "health_score > 0: healthy; < 0: faulty"


class SurrogateBundle(nn.Module):
    """POD + gappy layer + FDI network + health classifier (see the module docstring for the API).

    Args:
        pod: fitted :class:`POD` (n_e samples, n_m modes).
        indices: (n_w,) selected sample indices.
        network: trained :class:`FDIMLP` (or :class:`FDIEnsemble`) with n_m inputs.
        classifier: fitted :class:`HealthClassifier`.
        sample_rate: acquisition rate [Hz] (sample i is at t = i / sample_rate).
        residual_threshold: gappy residual [A] above which a signal is flagged out of distribution.
        full_residual_threshold: relative POD residual of a full record (:class:`FullSignalCheck`) above
            which it is flagged out of distribution (inf: no check; bundles saved without one).
        gappy_ridge: ridge of the gappy layer.
        gappy_statistics: ``noise_covariance`` (n_w, n_w) and ``prior_variance`` (n_m,) of the Bayesian gappy
            layer (:func:`~.gappy_pod.gappy_statistics`); None = plain least squares.
        meta: extra JSON-able provenance (selector, config, data) kept in ``meta["extra"]``.
        nominal_record: (n_e,) current [A] of the training model at the nominal fault vector (the store's
            ``nominal`` split); it lets a record of another bench be moved onto the training model with that
            bench's own healthy record (:meth:`~phm_torch.online.OnlinePipeline.rebase`). None: unknown.
        verdict_classifier: fitted :class:`HealthClassifier` of FDI estimates (:mod:`.verdict_classifier`),
            the verdict on a measured actuator; None: ``classifier`` gives it too.
        forward_model: fitted :class:`~.forward.ForwardSurrogate` k -> alpha, the online consistency check's
            (analysis by synthesis, :mod:`phm_torch.online.consistency`); None: no such check.
        roughness_threshold, plateau_threshold: the full-record check's shape thresholds
            (:func:`~.ood_calibration.shape_thresholds`; its physical defaults for bundles saved without them).
    """

    __jit_unused_properties__: ClassVar[list[str]] = [
        "verdict",
        "provenance",
    ]  # scripting exports the FDI; these are plain Python

    def __init__(
        self,
        pod: POD,
        indices: torch.Tensor,
        network: FDIMLP | FDIEnsemble,
        classifier: HealthClassifier,
        sample_rate: float,
        residual_threshold: float = float("inf"),
        gappy_ridge: float = 0.0,
        selector: Mapping[str, Any] | None = None,
        meta: Mapping[str, Any] | None = None,
        full_residual_threshold: float = float("inf"),
        gappy_statistics: Mapping[str, torch.Tensor] | None = None,
        nominal_record: torch.Tensor | None = None,
        verdict_classifier: HealthClassifier | None = None,
        forward_model: ForwardSurrogate | None = None,
        roughness_threshold: float = DEFAULT_ROUGHNESS_THRESHOLD,
        plateau_threshold: float = DEFAULT_PLATEAU_THRESHOLD,
    ):
        super().__init__()
        if network.n_inputs != pod.n_modes:
            raise ValueError(f"network has {network.n_inputs} inputs but the POD has {pod.n_modes} modes")
        self.pod = pod
        self.gappy_statistics = {k: v.detach().cpu() for k, v in (gappy_statistics or {}).items()}
        self.gappy = GappyPOD(pod.modes_, pod.mean_, indices, ridge=gappy_ridge, **self.gappy_statistics)
        self.network = network
        self.classifier = classifier
        self.verdict_classifier = verdict_classifier
        self.forward_model = forward_model
        self.sample_rate = float(sample_rate)
        self.selector_info = dict(selector or {})
        self.extra = dict(meta or {})
        self.register_buffer("sample_times", self.gappy.indices.to(torch.float64) / self.sample_rate)
        self.register_buffer("residual_threshold", torch.tensor(float(residual_threshold)))
        self.register_buffer("full_residual_threshold", torch.tensor(float(full_residual_threshold)))
        self.register_buffer("roughness_threshold", torch.tensor(float(roughness_threshold)))
        self.register_buffer("plateau_threshold", torch.tensor(float(plateau_threshold)))
        if nominal_record is not None and tuple(nominal_record.shape) != tuple(pod.mean_.shape):
            raise ValueError(
                f"nominal_record must have shape {tuple(pod.mean_.shape)}, got {tuple(nominal_record.shape)}"
            )
        self.nominal_record = None if nominal_record is None else nominal_record.detach().cpu()

    # ---- online API -------------------------------------------------------------------------------
    def full_signal_check(self) -> FullSignalCheck:
        """The out-of-distribution check of full records with this bundle's thresholds."""
        return FullSignalCheck(
            self.pod.modes_,
            self.pod.mean_,
            residual_threshold=float(self.full_residual_threshold),
            roughness_threshold=float(self.roughness_threshold),
            plateau_threshold=float(self.plateau_threshold),
        )

    @property
    def indices(self) -> torch.Tensor:
        return self.gappy.indices

    def compress(self, signals: torch.Tensor) -> torch.Tensor:
        """Selected samples (B, n_w) of full records (B, n_e) [A]."""
        if signals.shape[-1] != self.pod.mean_.shape[0]:
            raise ValueError(f"signals must have {self.pod.mean_.shape[0]} samples, got shape {tuple(signals.shape)}")
        return self.gappy.select(signals)

    def coefficients(
        self, samples: torch.Tensor, mask: torch.Tensor | None = None
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Gappy POD: alpha (B, n_m) and residual (B,) [A] from samples (B, n_w) [A]."""
        return self.gappy(samples, mask)

    def fdi(
        self, samples: torch.Tensor, mask: torch.Tensor | None = None, noise: torch.Tensor | None = None
    ) -> torch.Tensor:
        """Estimated fault vector k_hat (B, 8) in [0, 1] from samples (B, n_w) [A]; ``noise`` (B,) the records'
        relative noise, for a noise-aware network (None: its ``default_noise``)."""
        alpha, _ = self.gappy(samples, mask)
        return self.network(alpha, noise)

    def forward(self, samples: torch.Tensor, mask: torch.Tensor | None = None) -> torch.Tensor:
        """Same as :meth:`fdi` (the exported entry point)."""
        return self.fdi(samples, mask)

    @torch.no_grad()
    def estimate(self, signals: torch.Tensor, noise: torch.Tensor | None = None) -> torch.Tensor:
        """k_hat (B, 8) float64 of full records ``signals`` (B, n_e) [A], as the online pipeline estimates it:
        the selected samples, the network told ``noise`` (B,), each record's relative noise level (None:
        estimated from the record, :func:`~.augment.noise_level`)."""
        dtype = self.pod.mean_.dtype
        level = noise_level(signals.to(torch.float64)) if noise is None else noise
        return self.fdi(self.compress(signals.to(dtype)), noise=level.to(dtype)).double()

    def diagnose(
        self, samples: torch.Tensor, mask: torch.Tensor | None = None, noise: torch.Tensor | None = None
    ) -> dict[str, torch.Tensor]:
        """k_hat (B, 8), alpha (B, n_m), residual (B,) [A], out_of_distribution (B,) bool (``noise`` as
        :meth:`fdi`)."""
        alpha, residual = self.gappy(samples, mask)
        return {
            "k_hat": self.network(alpha, noise),
            "alpha": alpha,
            "residual": residual,
            "out_of_distribution": residual > self.residual_threshold,
        }

    def health_score(self, k: torch.Tensor) -> torch.Tensor:
        """Score f(k) - threshold (B,) float64 for fault vectors (B, 8): > 0 healthy, < 0 faulty."""
        return self.classifier(k) - self.classifier.threshold

    def is_healthy(self, k: torch.Tensor) -> torch.Tensor:
        """(B,) bool, the classifier's decision (f(k) > its threshold)."""
        return self.classifier.predict(k)

    @property
    def provenance(self) -> dict[str, Any]:
        """``{"actuator", "command"}`` records of the store it was trained on (``{}``: an older bundle)."""
        return dict(self.extra.get("provenance") or {})

    def check_store(self, store_provenance: Mapping[str, Any], where: str) -> None:
        """Raise a ValueError when the store (its ``provenance``) belongs to another actuator or test command
        than the one this bundle was trained for (a bundle or store without records passes)."""
        from ..provenance import require_same

        require_same(store_provenance, self.provenance, where)

    @property
    def verdict(self) -> HealthClassifier:
        """The classifier that judges FDI estimates: the verdict classifier, else the health classifier."""
        return self.classifier if self.verdict_classifier is None else self.verdict_classifier

    def verdict_score(self, k_hat: torch.Tensor) -> torch.Tensor:
        """Score g(k_hat) - threshold (B,) of FDI estimates (B, 8): > 0 healthy, < 0 faulty."""
        return self.verdict(k_hat) - self.verdict.threshold

    def verdict_healthy(self, k_hat: torch.Tensor) -> torch.Tensor:
        """(B,) bool, the verdict on actuators whose FDI estimates are k_hat (B, 8)."""
        return self.verdict.predict(k_hat)

    # ---- persistence ------------------------------------------------------------------------------
    def metadata(self) -> dict[str, Any]:
        """The ``meta`` block of the file (plain JSON-able values)."""
        return {
            "n_samples": int(self.pod.mean_.shape[0]),
            "n_modes": self.pod.n_modes,
            "n_points": self.gappy.n_points,
            "n_hidden": self.network.n_hidden,
            "n_layers": self.network.n_layers,
            "n_members": self.network.n_members,
            "input_scaling": self.network.input_scaling,
            "noise_input": self.network.noise_input,
            "default_noise": self.network.default_noise,
            "max_noise": self.network.max_noise,
            "sample_rate": self.sample_rate,
            "signal": "current",
            "unit": "A",
            "fault_names": list(FAULT_NAMES),
            "health_convention": HEALTH_CONVENTION,
            "selector": self.selector_info,
            "classifier": _spec(self.classifier),
            "verdict_classifier": _spec(self.verdict_classifier),
            "forward_model": None if self.forward_model is None else self.forward_model.get_params(),
            "gappy_ridge": self.gappy.ridge,
            "phm_torch_version": __version__,
            "extra": self.extra,
        }

    def save(self, path: str | os.PathLike) -> Path:
        """Write the bundle atomically to ``path`` (conventionally ``surrogates.pt``)."""
        tensors = {
            f"pod.{k}": getattr(self.pod, k).detach().cpu() for k in ("mean_", "modes_", "singular_values_", "energy_")
        }
        tensors.update(
            indices=self.indices.cpu(),
            sample_times=self.sample_times.cpu(),
            residual_threshold=self.residual_threshold.cpu(),
            full_residual_threshold=self.full_residual_threshold.cpu(),
            roughness_threshold=self.roughness_threshold.cpu(),
            plateau_threshold=self.plateau_threshold.cpu(),
        )
        tensors.update({f"gappy.{k}": v for k, v in self.gappy_statistics.items()})
        if self.nominal_record is not None:
            tensors["nominal_record"] = self.nominal_record
        tensors.update({f"network.{k}": v.detach().cpu() for k, v in self.network.state_dict().items()})
        for name in ("classifier", "verdict_classifier", "forward_model"):
            if getattr(self, name) is not None:
                tensors.update({f"{name}.{k}": v.detach().cpu() for k, v in getattr(self, name).state_dict().items()})
        return write_bundle_file(path, self.metadata(), tensors)

    @classmethod
    def load(
        cls, path: str | os.PathLike, expect: Mapping[str, Any] | None = None, map_location: str | torch.device = "cpu"
    ) -> SurrogateBundle:
        """Read a bundle written by :meth:`save` (``weights_only=True``).

        Args:
            expect: values the caller's configuration requires, e.g. ``{"n_modes": 22, "n_points": 30}``
                (keys among n_samples, n_modes, n_points, n_hidden, n_layers, n_members); a mismatch is a ValueError naming
                the field (a checkpoint from another configuration).
        """
        path = Path(path)
        meta, t = read_bundle_file(path, expect, map_location)
        parts = rebuild_parts(meta, t, path)
        bundle = cls(
            parts["pod"],
            t["indices"],
            parts["network"],
            parts["classifier"],
            meta["sample_rate"],
            float(t["residual_threshold"]),
            meta["gappy_ridge"],
            meta["selector"],
            meta["extra"],
            float(t.get("full_residual_threshold", float("inf"))),
            _prefixed(t, "gappy.") or None,
            t.get("nominal_record"),
            parts["verdict_classifier"],
            parts["forward_model"],
            float(t.get("roughness_threshold", DEFAULT_ROUGHNESS_THRESHOLD)),
            float(t.get("plateau_threshold", DEFAULT_PLATEAU_THRESHOLD)),
        )
        return bundle.eval()
