"""A near-nominal FDI for life tracking: a network on the pipeline's own gappy coefficients, trained where an
actuator spends its life (every damage below ~0.2), read instead of the pipeline's k_hat where that says near
nominal.

The pipeline's FDI is trained on the importance-sampled store, which spends most of its records on large faults; the
tracker reads it near nominal, where its errors (0.004 rms per damage on the reference actuator, 0.009 for
eccentricity, with a biased mean response, :mod:`.response`) set the prognostic horizon and the end-of-life flags.
The same inputs (the 40 gappy coefficients of the 1000 selected samples) read by a network trained on near-nominal
records only give 2-3 times smaller errors there (docs/prognostics.md, "A near-nominal FDI"); its error then grows
with the noise, so a network can instead read every sample of the record on its own principal basis (``n_full``),
2-4 times more precise again (the shipped one; "The shipped near-nominal FDI reads the whole record"). The network is gated
by the pipeline's own estimate: used where its largest damage is at most ``gate`` and the record's noise at most
the last calibrated noise level; elsewhere the pipeline's k_hat stands. The gate reads only the components the
pipeline identifies (``gate_components_``): one its test command does not identify reads its training prior, which
on a store sampled far from nominal (a robust actuator) sat above the gate for almost every new actuator and shut
the network out where it is made to be read. It is told each record's noise level (the
noise-aware networks' input); its 90 % half-widths are calibrated on held-out histories at each of its noise levels,
per component.

Saved as a dict of tensors (``torch.save``, read back with ``weights_only=True``) with a JSON header holding the
settings and the provenance: the pipeline it reads (its :func:`~.response.probe_k_hat`), actuator, command, data.
"""

from __future__ import annotations

import itertools
import json
import math
import os
import pickle
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any

import torch
from torch import nn

from ..faults import FAULT_NAMES, N_FAULTS
from ..io.atomic import atomic_open
from ..online.noise_threshold import interpolate_levels
from ..surrogates.metrics import IDENTIFIED_R2, fdi_identifiability
from .response import check_probe

FORMAT = "phm_torch.near_nominal_fdi/1"
Z95 = 1.6448536269514722
NOISE_UNIT = 0.01  # the noise input is the relative level in percent
PHASE_INDEX = FAULT_NAMES.index("eccentricity_phase")  # not a damage: never gated on, always the pipeline's
# A full record with up to this share of its samples missing is read by least squares on the samples it has: a record
# aligned on its trigger misses its last milliseconds (0.5-10 ms: up to 2 %), which otherwise left the tracker on the
# pipeline's 5-10x less precise near-nominal estimate at every inspection of such a bench.
MISSING_MAX = 0.05


class TooFewNearNominalRecords(ValueError):
    """The life histories hold too few records to train the near-nominal FDI on or to calibrate it with."""


class NearNominalFDI(nn.Module):
    """MLP gappy coefficients alpha (B, n_m) [A] -> k (B, 8), for records near nominal.

    Args:
        n_modes: coefficients read: the pipeline's POD modes, or with ``n_full`` the modes of its own basis.
        n_hidden, n_layers: tanh layers.  nominal: (8,) nominal fault vector.
        gate: largest damage |k_hat - nominal| of the pipeline's own estimate up to which this network is read.
        noise_levels: increasing relative noise levels its half-widths are calibrated at; it is read up to the last.
        n_full: None (reads the pipeline's gappy coefficients of its selected samples), or the samples of a full
            record (10001): it reads the record's projection on its own orthonormal basis (``basis_``), every
            sample (white noise averages over 10x more samples than the selected ones).

    Fitted buffers: ``input_mean_``, ``input_std_`` (n_m,) coefficient scaling; ``half_widths_`` (n_levels, 8)
    calibrated 90 % half-widths [k units] of its estimates at ``noise_levels`` (NaN until calibrated); ``r2_``
    (n_levels, 8) their R^2 on the same held-out records (NaN in a file calibrated before it was measured);
    ``gate_components_`` (8,) bool, the pipeline's components the gate reads (:meth:`gate_on`; every damage until
    set, never the eccentricity phase); with
    ``n_full``: ``record_mean_`` (n_full,) [A] and ``basis_`` (n_full, n_m) orthonormal columns (:meth:`fit_basis`;
    stored in float32).
    """

    def __init__(
        self,
        n_modes: int,
        n_hidden: int = 256,
        n_layers: int = 2,
        nominal: Sequence[float] | None = None,
        gate: float = 0.25,
        noise_levels: Sequence[float] = (0.01, 0.02, 0.03, 0.04),
        n_full: int | None = None,
    ):
        super().__init__()
        if isinstance(n_modes, bool) or not isinstance(n_modes, int) or n_modes < 1:
            raise ValueError(f"near_nominal.n_modes must be a positive integer, got {n_modes!r}")
        if not 0.0 < float(gate) <= 1.0:
            raise ValueError(f"near_nominal.gate must be in (0, 1], got {gate!r}")
        levels = [float(v) for v in noise_levels]
        if not levels or levels[0] <= 0.0 or any(b <= a for a, b in itertools.pairwise(levels)):
            raise ValueError(f"near_nominal.noise_levels must be positive and increasing, got {list(noise_levels)}")
        self.n_modes, self.n_hidden, self.n_layers = n_modes, int(n_hidden), int(n_layers)
        self.gate, self.noise_max = float(gate), levels[-1]
        layers: list[nn.Module] = []
        width = n_modes + 1  # the coefficients and the record's noise level
        for _ in range(self.n_layers):
            layers += [nn.Linear(width, self.n_hidden), nn.Tanh()]
            width = self.n_hidden
        layers.append(nn.Linear(width, N_FAULTS))
        self.net = nn.Sequential(*layers).double()
        nominal = torch.tensor([0.0] * 6 + [0.5, 0.5] if nominal is None else list(nominal), dtype=torch.float64)
        self.register_buffer("nominal", nominal)
        self.register_buffer("input_mean_", torch.zeros(n_modes, dtype=torch.float64))
        self.register_buffer("input_std_", torch.ones(n_modes, dtype=torch.float64))
        self.register_buffer("noise_levels", torch.tensor(levels, dtype=torch.float64))
        self.register_buffer("half_widths_", torch.full((len(levels), N_FAULTS), math.nan, dtype=torch.float64))
        self.register_buffer("r2_", torch.full((len(levels), N_FAULTS), math.nan, dtype=torch.float64))
        self.register_buffer("gate_components_", self.default_gate_components())
        if n_full is not None and (isinstance(n_full, bool) or not isinstance(n_full, int) or n_full <= n_modes):
            raise ValueError(f"near_nominal.n_full must be an integer above n_modes ({n_modes}), got {n_full!r}")
        self.n_full = n_full
        # (basis_'s identity, basis_ in float64, its Gram matrix)
        self._basis64: tuple[Any, torch.Tensor, torch.Tensor] | None = None
        if n_full is not None:
            self.register_buffer("record_mean_", torch.zeros(n_full, dtype=torch.float64))
            # float32: the file's largest tensor at half the size; the projection is summed in float64
            self.register_buffer("basis_", torch.zeros(n_full, n_modes, dtype=torch.float32))
        self.provenance: dict[str, Any] = {}

    def coefficients(self, model: Any, current: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(coefficients (B, n_m) float64, readable (B,) bool) of full records ``current`` (B, n_full) [A] read by
        ``model`` (the pipeline): their projection on this network's basis, or the pipeline's gappy coefficients of
        its selected samples. On its own basis a record missing at most ``MISSING_MAX`` of its samples (NaN) is read
        by least squares on the samples it has (its projection, for a record in the basis's span); one missing more,
        or with the pipeline's selected samples any, is not readable (zeros there)."""
        if self.n_full is None:
            samples = current.index_select(1, model.gappy.indices).to(model.gappy.modes_hat.dtype)
            readable = torch.isfinite(samples).all(1)
            alpha = model.gappy(torch.where(readable.unsqueeze(1), samples, torch.zeros_like(samples)))[0]
            return alpha.to(torch.float64), readable
        if current.dim() != 2 or current.shape[1] != self.n_full:
            raise ValueError(f"near-nominal FDI: records (B, {self.n_full}) expected, got {tuple(current.shape)}")
        x = current.to(torch.float64)
        present = torch.isfinite(x)
        readable = (~present).double().mean(1) <= MISSING_MAX
        x = torch.where(present & readable.unsqueeze(1), x - self.record_mean_, torch.zeros_like(x))
        # cast once, not at every record (~1 ms); made again whenever basis_ changed (fit, load_state_dict, .to)
        key = (self.basis_.data_ptr(), self.basis_._version, x.device)
        if self._basis64 is None or self._basis64[0] != key:
            basis = self.basis_.to(device=x.device, dtype=torch.float64)
            self._basis64 = (key, basis, basis.T @ basis)
        _, basis, gram = self._basis64
        alpha = x @ basis  # with the missing samples at zero: the right-hand side of their least squares
        for i in (readable & ~present.all(1)).nonzero().flatten().tolist():  # few, each its own normal equations:
            missing = basis[~present[i]]  # the Gram matrix of the samples it has is the whole one less the missing
            alpha[i] = torch.linalg.solve(gram - missing.T @ missing, alpha[i])
        return alpha, readable

    @torch.no_grad()
    def fit_basis(self, records: torch.Tensor) -> torch.Tensor:
        """Set ``record_mean_`` and ``basis_`` to the mean and the first n_m principal directions of training records
        (N, n_full) [A] (their SVD about the mean); returns the fraction (n_m,) of their variance about the mean each
        direction holds. Orthonormal columns: white noise of std sigma per sample is white of std sigma on every
        coefficient, which is how the fit adds noise to them."""
        if self.n_full is None:
            raise ValueError("near-nominal FDI: fit_basis needs n_full (a full-record network)")
        if records.dim() != 2 or records.shape[1] != self.n_full or records.shape[0] <= self.n_modes:
            raise ValueError(
                f"near-nominal FDI: more than {self.n_modes} records (N, {self.n_full}) needed, got {tuple(records.shape)}"
            )
        x = records.to(torch.float64)
        mean = x.mean(0)
        _, sv, vh = torch.linalg.svd(x - mean, full_matrices=False)
        self.record_mean_.copy_(mean)
        self.basis_.copy_(vh[: self.n_modes].T)
        return (sv[: self.n_modes] ** 2) / (sv**2).sum()

    def forward(self, alpha: torch.Tensor, noise: torch.Tensor) -> torch.Tensor:
        """Estimates k (B, 8) of records with gappy coefficients alpha (B, n_m) and relative noise (B,)."""
        return self.net(self._features(alpha, noise)).clamp(0.0, 1.0)

    def _features(self, alpha: torch.Tensor, noise: torch.Tensor) -> torch.Tensor:
        scaled = (alpha.to(torch.float64) - self.input_mean_) / self.input_std_
        return torch.cat([scaled, (noise.to(torch.float64) / NOISE_UNIT).unsqueeze(1)], 1)

    def half_widths(self, noise: torch.Tensor) -> torch.Tensor:
        """(B, 8) calibrated 90 % half-widths at the records' noise (B,), linear between the calibrated levels and
        held at the first and last."""
        # per component, the pipeline's own interpolation of calibrated levels
        return torch.stack(
            [interpolate_levels(self.noise_levels, self.half_widths_[:, j], noise) for j in range(N_FAULTS)], 1
        )

    def not_identified(self, noise: float) -> list[str] | None:
        """The components whose held-out R^2 at the record's relative ``noise`` (interpolated between the
        calibrated levels) is below :data:`~phm_torch.surrogates.metrics.IDENTIFIED_R2` (their reading is the
        training prior near nominal), or None where the file does not carry R^2 (calibrated before it was)."""
        if bool(torch.isnan(self.r2_).any()):
            return None
        x = torch.tensor([float(noise)], dtype=torch.float64)
        r2 = [float(interpolate_levels(self.noise_levels, self.r2_[:, j], x)[0]) for j in range(N_FAULTS)]
        return [n for n, v in zip(FAULT_NAMES, r2) if not v >= IDENTIFIED_R2]

    @staticmethod
    def default_gate_components() -> torch.Tensor:
        """(8,) bool: every damage, not the eccentricity phase (the gate of a pipeline without identifiability)."""
        on = torch.ones(N_FAULTS, dtype=torch.bool)
        on[PHASE_INDEX] = False
        return on

    def gate_on(self, not_identified: Sequence[str]) -> None:
        """Gate on the pipeline's components but ``not_identified`` (fault names; the pipeline's
        :func:`~phm_torch.online.diagnosis.not_identified`). ValueError for an unknown name, or for none left."""
        unknown = [n for n in not_identified if n not in FAULT_NAMES]
        if unknown:
            raise ValueError(f"near-nominal FDI: unknown fault names {unknown}; known: {list(FAULT_NAMES)}")
        on = self.default_gate_components()
        for name in not_identified:
            on[FAULT_NAMES.index(name)] = False
        if not bool(on.any()):
            raise ValueError("near-nominal FDI: the pipeline identifies no damage to gate on")
        self.gate_components_.copy_(on)

    def gated(self, k_pipeline: torch.Tensor, noise: torch.Tensor) -> torch.Tensor:
        """(B,) bool: where this network is read, given the pipeline's k_hat (B, 8) and the records' noise (B,)."""
        damage = (k_pipeline.to(torch.float64) - self.nominal).abs()
        damage = torch.where(self.gate_components_, damage, torch.zeros_like(damage))
        return (damage.amax(1) <= self.gate) & (noise.to(torch.float64) <= self.noise_max)

    @torch.no_grad()
    def read(
        self, alpha: torch.Tensor, k_pipeline: torch.Tensor, noise: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
        """(used (B,) bool, k (B, 8), lower (B, 8), upper (B, 8)): this network's estimates and calibrated intervals
        where gated (the phase component stays the pipeline's), the pipeline's k_hat with NaN bounds elsewhere."""
        if not bool(torch.isfinite(self.half_widths_).all()):
            raise ValueError("near-nominal FDI: not calibrated (half_widths_ NaN)")
        used = self.gated(k_pipeline, noise)
        mine = self(alpha, noise)
        mine[:, PHASE_INDEX] = k_pipeline[:, PHASE_INDEX].to(torch.float64)
        k = torch.where(used.unsqueeze(1), mine, k_pipeline.to(torch.float64))
        w = self.half_widths(noise)
        lower, upper = (k - w).clamp(0.0, 1.0), (k + w).clamp(0.0, 1.0)
        nan = torch.full_like(k, math.nan)
        lower = torch.where(used.unsqueeze(1), lower, nan)
        upper = torch.where(used.unsqueeze(1), upper, nan)
        return used, k, lower, upper

    def calibrate(
        self, level: int, alpha: torch.Tensor, k_true: torch.Tensor, k_pipeline: torch.Tensor, noise: torch.Tensor
    ) -> tuple[torch.Tensor, int]:
        """Set row ``level`` of ``half_widths_`` (the calibrated noise level ``noise_levels[level]``) to the 90 %
        half-width of a Gaussian of the estimates' rms error per component, on held-out records at that noise
        (alpha (N, n_m), true k (N, 8), noise (N,)) that the gate admits (the pipeline's k_hat (N, 8)); returns (that
        rms (8,), the number of records). Row ``level`` of ``r2_`` gets their R^2 about the records' own mean."""
        used = self.gated(k_pipeline, noise)
        if int(used.sum()) < 20:
            raise TooFewNearNominalRecords(
                f"near-nominal FDI: {int(used.sum())} held-out records within the gate, 20 needed"
            )
        with torch.no_grad():
            truth = k_true[used].to(torch.float64)
            estimate = self(alpha[used], noise[used])
            rms = (estimate - truth).pow(2).mean(0).sqrt()
        self.half_widths_[level] = Z95 * rms
        # a component that does not vary over these records (NaN) is not identified either
        self.r2_[level] = torch.tensor(fdi_identifiability(estimate, truth), dtype=torch.float64).nan_to_num(-1.0)
        return rms, int(used.sum())

    def check_for(self, model: Any, source: str) -> None:
        """Raise ValueError unless this network was trained on ``model``'s gappy coefficients (its probe k_hat)."""
        check_probe(self.provenance, model, source, "near-nominal FDI", "trained")
        if self.n_full is not None:
            if int(model.n_full) != self.n_full:
                raise ValueError(f"near-nominal FDI reads records of {self.n_full} samples, {source} {model.n_full}")
        elif int(model.gappy.modes_hat.shape[1]) != self.n_modes:
            raise ValueError(
                f"near-nominal FDI reads {self.n_modes} coefficients, {source} has {model.gappy.modes_hat.shape[1]}"
            )

    def header(self) -> dict[str, Any]:
        return {
            "format": FORMAT,
            "n_modes": self.n_modes,
            "n_hidden": self.n_hidden,
            "n_layers": self.n_layers,
            "gate": self.gate,
            "noise_levels": self.noise_levels.tolist(),
            "n_full": self.n_full,
            "provenance": self.provenance,
        }

    def save(self, path: str | os.PathLike) -> None:
        """Write the tensors and the JSON header (one file), atomically."""
        with atomic_open(Path(path), "wb") as fh:
            torch.save({"header": json.dumps(self.header()), "state": self.state_dict()}, fh)

    @classmethod
    def load(cls, path: str | os.PathLike) -> NearNominalFDI:
        """Read a file written by :meth:`save` (``weights_only=True``: tensors and strings only)."""
        try:
            data = torch.load(Path(path), map_location="cpu", weights_only=True)
            header = json.loads(data["header"])
        except (OSError, RuntimeError, KeyError, TypeError, ValueError, pickle.UnpicklingError) as exc:
            raise ValueError(f"near-nominal FDI {path}: cannot read it ({exc})") from exc
        if header.get("format") != FORMAT:
            raise ValueError(f"near-nominal FDI {path}: not a {FORMAT} file (format {header.get('format')!r})")
        state: Mapping[str, torch.Tensor] = data["state"]
        model = cls(
            header["n_modes"],
            header["n_hidden"],
            header["n_layers"],
            state["nominal"].tolist(),
            header["gate"],
            header["noise_levels"],
            header.get("n_full"),
        )
        if "r2_" not in state:  # calibrated before R^2 was measured: unknown (the pipeline's identifiability stands)
            state = {**state, "r2_": torch.full_like(model.r2_, math.nan)}
        if "gate_components_" not in state:  # from before the gate read identified components only: every damage
            state = {**state, "gate_components_": cls.default_gate_components()}
        model.load_state_dict(state)
        model.provenance = dict(header.get("provenance", {}))
        return model.eval()


def fit_near_nominal(
    model: NearNominalFDI,
    alpha: torch.Tensor,
    noise: torch.Tensor,
    k_true: torch.Tensor,
    steps: int = 40000,
    batch_size: int = 256,
    lr: float = 2e-3,
    seed: int = 0,
    fresh: Callable[[], tuple[torch.Tensor, torch.Tensor, torch.Tensor]] | None = None,
) -> NearNominalFDI:
    """Train ``model`` (Adam, cosine decay) on coefficients alpha (N, n_m), the records' relative noise (N,) and
    true k (N, 8); the eccentricity phase is not a target. ``fresh``: None, or a callable () -> (alpha, noise, k)
    redrawing the training rows (new noise) every 2,000 steps. Returns the model (eval mode)."""
    if (
        alpha.ndim != 2
        or alpha.shape[1] != model.n_modes
        or k_true.shape != (alpha.shape[0], N_FAULTS)
        or noise.shape != alpha.shape[:1]
    ):
        raise ValueError(
            f"near-nominal FDI: alpha (N, {model.n_modes}), noise (N,) and k (N, 8) expected, got "
            f"{tuple(alpha.shape)}, {tuple(noise.shape)}, {tuple(k_true.shape)}"
        )
    gen = torch.Generator().manual_seed(seed)
    torch.manual_seed(seed)
    for layer in model.net:
        if isinstance(layer, nn.Linear):
            layer.reset_parameters()
    model.input_mean_.copy_(alpha.to(torch.float64).mean(0))
    model.input_std_.copy_(alpha.to(torch.float64).std(0).clamp(min=1e-12))
    weight = torch.ones(N_FAULTS, dtype=torch.float64)
    weight[PHASE_INDEX] = 0.0
    opt = torch.optim.Adam(model.net.parameters(), lr=lr)
    sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, steps)
    model.train()
    a, n, k = alpha, noise, k_true
    for step in range(steps):
        if fresh is not None and step and step % 2000 == 0:
            a, n, k = fresh()
        rows = torch.randint(0, a.shape[0], (batch_size,), generator=gen)
        pred = model.net(model._features(a[rows], n[rows]))
        loss = ((pred - k[rows].to(torch.float64)).pow(2) * weight).mean()
        opt.zero_grad()
        loss.backward()
        opt.step()
        sched.step()
    return model.eval()
