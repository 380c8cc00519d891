"""Analysis by synthesis: a forward surrogate k -> POD coefficients, and the consistency statistic it gives.

The FDI maps a record's POD coefficients alpha (22 numbers on the paper store) to a fault vector k_hat (8).
Every actuator of the training population produces coefficients on an 8-dimensional surface inside the
22-dimensional POD span; a corrupted record (shifted against its command, sign-flipped, another actuator's)
can lie in the span, and so pass the POD-residual checks, without lying on that surface. The FDI still
answers with some k_hat. :class:`ForwardSurrogate` learns the surface, k -> alpha(k), so that the record
k_hat *should* produce, ``mean + modes @ alpha(k_hat)``, can be compared with the record measured:
:func:`consistency_statistic` is the RMS of their difference over the record's RMS, divided by the scale
a good record reaches, sqrt(noise^2 + floor^2) (noise: the record's relative white-noise level; floor: the
relative residual of noise-free held-out records of the training store at the FDI's own answer). A record
whose statistic exceeds its calibrated threshold (:mod:`phm_torch.online.consistency`) is one the FDI's own
answer cannot reproduce: out of distribution, reason ``inconsistent``.

The network: inputs k with the eccentricity phase k7 replaced by (k6' cos 2 pi k7, k6' sin 2 pi k7) (k6' the
eccentricity's offset from nominal: the phase only matters with an eccentricity, and is periodic), each
input standardised with the training statistics; ``n_layers`` tanh layers of ``n_hidden``; output alpha in
amperes (scaled back by one common scale, so the loss is the record-space squared error: every mode
counts by its amperes, as in the residual).
"""

from __future__ import annotations

import math
import time
from typing import Any

import torch
from torch import nn

from ..faults import N_FAULTS
from .full_signal_check import record_stride
from .metrics import ECC_AMPLITUDE, ECC_PHASE


def _positive_int(value: Any, name: str) -> int:
    if isinstance(value, bool) or not isinstance(value, int) or value < 1:
        raise ValueError(f"forward.{name} must be a positive integer, got {value!r}")
    return value


class ForwardSurrogate(nn.Module):
    """Batch-first MLP k (B, 8) -> POD coefficients alpha (B, n_modes) [A]; TorchScript-able.

    Args:
        n_modes: POD modes n_m predicted.
        n_hidden: tanh neurons per hidden layer.   n_layers: hidden layers.
        nominal_eccentricity: k6 at nominal (the phase features are scaled by k6 - this).
        max_epochs, patience: Adam epochs at most, and without improvement of the held-out error before stopping.
        lr: Adam learning rate.   batch_size: rows per step.   holdout: fraction of the rows held out to stop
        on and to measure ``error_`` (0 < holdout < 0.5).   seed: initialisation, shuffling and the held-out draw.

    Fitted buffers:
        input_mean_, input_std_ (9,): feature standardisation.   alpha_mean_ (n_m,) [A], alpha_scale_ () [A]:
        output scaling.   error_ () [A]: held-out (weighted) RMS error per coefficient vector, ||alpha - f(k)||
        (record RMS x sqrt(n_e) for orthonormal modes).   floor_full_, floor_samples_ (): relative record residual at
        the FDI's estimates of noise-free held-out records, on the full record's rows and on the selected
        samples (set by :func:`~phm_torch.online.consistency.fit_forward_check`; 0 until then).
        best_epoch_ (int), n_fit_ (int).
    """

    __constants__ = ("n_modes", "n_faults", "ecc_amplitude", "ecc_phase")

    def __init__(
        self,
        n_modes: int,
        n_hidden: int = 64,
        n_layers: int = 2,
        nominal_eccentricity: float = 0.0,
        max_epochs: int = 600,
        patience: int = 60,
        lr: float = 3e-3,
        batch_size: int = 256,
        holdout: float = 0.1,
        seed: int = 0,
    ):
        super().__init__()
        self.n_modes = _positive_int(n_modes, "n_modes")
        self.n_hidden, self.n_layers = _positive_int(n_hidden, "n_hidden"), _positive_int(n_layers, "n_layers")
        self.max_epochs, self.patience = _positive_int(max_epochs, "max_epochs"), _positive_int(patience, "patience")
        self.batch_size = _positive_int(batch_size, "batch_size")
        if not lr > 0:
            raise ValueError(f"forward.lr must be > 0, got {lr!r}")
        if not 0.0 < holdout < 0.5:
            raise ValueError(f"forward.holdout must be in (0, 0.5), got {holdout!r}")
        self.lr, self.holdout, self.seed = float(lr), float(holdout), int(seed)
        self.nominal_eccentricity = float(nominal_eccentricity)
        self.n_faults, self.ecc_amplitude, self.ecc_phase = (
            N_FAULTS,
            ECC_AMPLITUDE,
            ECC_PHASE,
        )  # TorchScript reads no globals
        n_in = N_FAULTS + 1
        layers: list[nn.Module] = []
        for i in range(self.n_layers):
            layers += [nn.Linear(n_in if i == 0 else self.n_hidden, self.n_hidden), nn.Tanh()]
        layers.append(nn.Linear(self.n_hidden, self.n_modes))
        self.net = nn.Sequential(*layers)
        self.register_buffer("input_mean_", torch.zeros(n_in))
        self.register_buffer("input_std_", torch.ones(n_in))
        self.register_buffer("alpha_mean_", torch.zeros(self.n_modes))
        self.register_buffer("alpha_scale_", torch.tensor(1.0))
        self.register_buffer("error_", torch.tensor(float("nan")))
        self.register_buffer("floor_full_", torch.tensor(0.0))
        self.register_buffer("floor_samples_", torch.tensor(0.0))
        self.best_epoch_, self.n_fit_ = -1, 0

    def get_params(self) -> dict[str, Any]:
        """Constructor arguments (JSON-able), as the bundle stores them."""
        return {
            "n_modes": self.n_modes,
            "n_hidden": self.n_hidden,
            "n_layers": self.n_layers,
            "nominal_eccentricity": self.nominal_eccentricity,
            "max_epochs": self.max_epochs,
            "patience": self.patience,
            "lr": self.lr,
            "batch_size": self.batch_size,
            "holdout": self.holdout,
            "seed": self.seed,
        }

    def features(self, k: torch.Tensor) -> torch.Tensor:
        """(B, 9) raw features of k (B, 8): k without k7, then the eccentricity offset times cos and sin 2 pi k7."""
        ecc = k[:, self.ecc_amplitude] - self.nominal_eccentricity
        angle = 2.0 * math.pi * k[:, self.ecc_phase]
        rest = torch.cat([k[:, : self.ecc_phase], k[:, self.ecc_phase + 1 :]], dim=1)
        return torch.cat([rest, (ecc * torch.cos(angle)).unsqueeze(1), (ecc * torch.sin(angle)).unsqueeze(1)], dim=1)

    def forward(self, k: torch.Tensor) -> torch.Tensor:
        """alpha (B, n_modes) [A] of fault vectors k (B, 8)."""
        if k.dim() != 2 or k.shape[1] != self.n_faults:
            raise ValueError("forward surrogate: k must be (B, 8)")
        x = (self.features(k.to(self.input_mean_.dtype)) - self.input_mean_) / self.input_std_
        return self.alpha_mean_ + self.alpha_scale_ * self.net(x)

    def fit(self, k: torch.Tensor, alpha: torch.Tensor, weight: torch.Tensor | None = None) -> ForwardSurrogate:
        """Fit to fault vectors k (N, 8) and their records' POD coefficients alpha (N, n_modes) [A]; returns self.

        Adam on the weighted mean squared error of alpha / alpha_scale_, a random ``holdout`` fraction of the
        rows held out; the weights of the epoch with the lowest held-out error are kept (early stopping after
        ``patience`` epochs without improvement). Deterministic for a given ``seed`` (one thread).

        ``weight`` (N,) > 0: each row's weight (None: equal). The records' currents span decades (0.65 to 400 A
        RMS on an LF store: a few heavy shorts), so :func:`fit_forward_check` weighs each by 1 / its mean square:
        the loss is then the relative residual the consistency statistic measures, not the few largest records'."""
        if k.dim() != 2 or k.shape[1] != N_FAULTS or alpha.dim() != 2 or alpha.shape != (k.shape[0], self.n_modes):
            raise ValueError(
                f"forward.fit: k must be (N, 8) and alpha (N, {self.n_modes}), got {tuple(k.shape)} "
                f"and {tuple(alpha.shape)}"
            )
        n = k.shape[0]
        n_hold = max(1, round(self.holdout * n))
        if n - n_hold < 2:
            raise ValueError(f"forward.fit: {n} rows leave too few to fit with holdout={self.holdout}")
        if not (bool(torch.isfinite(k).all()) and bool(torch.isfinite(alpha).all())):
            raise ValueError("forward.fit: k and alpha must be finite")
        weight = torch.ones(n) if weight is None else weight.to(self.input_mean_.dtype)
        if weight.shape != (n,) or not bool((weight > 0).all()):
            raise ValueError(f"forward.fit: weight must be (N,) = ({n},) and > 0")
        gen = torch.Generator().manual_seed(self.seed)
        with torch.random.fork_rng(devices=[]):
            torch.manual_seed(self.seed)
            for layer in self.net:
                if isinstance(layer, nn.Linear):
                    layer.reset_parameters()
        dtype = self.input_mean_.dtype
        k, alpha = k.to(dtype), alpha.to(dtype)
        perm = torch.randperm(n, generator=gen)
        hold, rows = perm[:n_hold], perm[n_hold:]
        feats = self.features(k)
        self.input_mean_ = feats[rows].mean(0)
        self.input_std_ = feats[rows].std(0).clamp(min=1e-6)
        weight = (weight / weight[rows].mean()).to(dtype)
        w = weight[rows].unsqueeze(1)
        self.alpha_mean_ = (w * alpha[rows]).sum(0) / w.sum()
        self.alpha_scale_ = (
            (w.squeeze(1) * (alpha[rows] - self.alpha_mean_).pow(2).sum(1)).mean().sqrt().clamp(min=1e-12)
        )
        x = (feats - self.input_mean_) / self.input_std_
        target = (alpha - self.alpha_mean_) / self.alpha_scale_
        optimizer = torch.optim.Adam(self.net.parameters(), lr=self.lr)
        scheduler = torch.optim.lr_scheduler.ReduceLROnPlateau(
            optimizer, factor=0.5, patience=max(1, self.patience // 3)
        )
        best, best_state, best_epoch = float("inf"), None, -1
        for epoch in range(self.max_epochs):
            self.net.train()
            for batch in rows[torch.randperm(rows.numel(), generator=gen)].split(self.batch_size):
                optimizer.zero_grad()
                with torch.enable_grad():  # also under a caller's no_grad
                    loss = (weight[batch] * (self.net(x[batch]) - target[batch]).pow(2).sum(1)).mean()
                    loss.backward()
                optimizer.step()
            with torch.no_grad():
                held = float((weight[hold] * (self.net(x[hold]) - target[hold]).pow(2).sum(1)).mean())
            scheduler.step(held)
            if held < best:
                best, best_epoch = held, epoch
                best_state = {key: v.detach().clone() for key, v in self.net.state_dict().items()}
            elif epoch - best_epoch >= self.patience:
                break
        if best_state is not None:
            self.net.load_state_dict(best_state)
        self.net.eval()
        self.error_ = torch.tensor(best, dtype=dtype).sqrt() * self.alpha_scale_
        self.best_epoch_, self.n_fit_ = best_epoch, int(rows.numel())
        return self

    def summary(self) -> dict[str, float]:
        """Fit figures: held-out RMS coefficient error [A] and relative to the coefficients' spread, the residual
        floors, best epoch, rows fitted, wall time [s]."""
        return {
            "error": float(self.error_),
            "relative_error": float(self.error_ / self.alpha_scale_),
            "floor_full": float(self.floor_full_),
            "floor_samples": float(self.floor_samples_),
            "best_epoch": self.best_epoch_,
            "n_fit": self.n_fit_,
            "fit_s": round(getattr(self, "fit_s_", 0.0), 2),
        }

    def extra_repr(self) -> str:
        return f"n_modes={self.n_modes}, n_hidden={self.n_hidden}, n_layers={self.n_layers}"


def consistency_statistic(
    y: torch.Tensor,
    mean: torch.Tensor,
    modes: torch.Tensor,
    alpha_pred: torch.Tensor,
    noise: torch.Tensor,
    floor: torch.Tensor,
) -> torch.Tensor:
    """Normalised residual (B,) between measured records and the records their predicted coefficients give.

    Args:
        y: (B, n) measured current [A] at n samples (a full record's rows, or its selected samples); NaN = missing.
        mean: (n,) POD mean at those samples [A].   modes: (n, n_m) POD modes at those samples.
        alpha_pred: (B, n_m) predicted coefficients [A] (the forward surrogate at the FDI's k_hat).
        noise: (B,) the records' relative white-noise level (noise std over the record's RMS).
        floor: () relative residual of good noise-free records (:attr:`ForwardSurrogate.floor_full_` or
            ``floor_samples_``).

    Returns:
        RMS(y - mean - modes alpha_pred) / RMS(y) / sqrt(noise^2 + floor^2), over the finite samples; ~1 or
        below for a record the prediction reproduces to its noise, NaN with no finite sample.
    """
    r = y - mean - alpha_pred.to(y.dtype) @ modes.T
    present = torch.isfinite(r)
    r = torch.where(present, r, torch.zeros_like(r))
    yp = torch.where(present, y, torch.zeros_like(y))
    ratio = (r.pow(2).sum(1) / yp.pow(2).sum(1).clamp(min=1e-30)).sqrt()
    scale = (noise.to(y.dtype).pow(2) + floor.to(y.dtype).pow(2)).sqrt().clamp(min=1e-12)
    return torch.where(present.any(1), ratio / scale, torch.full_like(ratio, float("nan")))


@torch.no_grad()
def fit_forward_check(
    pod: nn.Module,
    gappy: nn.Module,
    network: nn.Module,
    k: torch.Tensor,
    current: torch.Tensor,
    nominal: torch.Tensor | None = None,
    seed: int = 0,
    block_rows: int = 2048,
    **params: Any,
) -> ForwardSurrogate:
    """A forward surrogate fitted on a store's training records, with its residual floors.

    Args:
        pod: the bundle's fitted :class:`~.pod.POD` (n_e samples, n_m modes).  gappy: its gappy layer.
        network: its FDI network (alpha [, noise] -> k_hat).
        k: (N, 8) fault vectors of the training records.  current: (N, n_e) their records [A].
        nominal: (8,) nominal fault vector (its eccentricity centres the phase features; None: 0).
        seed: the surrogate's seed.  params: other :class:`ForwardSurrogate` arguments.

    The targets are the records' full POD projections (:func:`fit_forward_on_coefficients` does the rest)."""
    t0 = time.perf_counter()
    alpha = torch.cat(
        [pod(current[i : i + block_rows].to(pod.mean_.dtype)) for i in range(0, len(current), block_rows)]
    )
    model = fit_forward_on_coefficients(
        alpha, k, current, gappy, network, pod.mean_, pod.modes_, nominal, seed, block_rows, **params
    )
    model.fit_s_ = time.perf_counter() - t0
    return model


@torch.no_grad()
def fit_forward_on_coefficients(
    alpha: torch.Tensor,
    k: torch.Tensor,
    current: torch.Tensor,
    gappy: nn.Module,
    network: nn.Module,
    mean: torch.Tensor,
    modes: torch.Tensor,
    nominal: torch.Tensor | None = None,
    seed: int = 0,
    block_rows: int = 2048,
    **params: Any,
) -> ForwardSurrogate:
    """A forward surrogate fitted to given POD coefficients of training records, with its residual floors.

    Args:
        alpha: (N, n_m) the records' POD coefficients, the targets (a bundle's full projections, or, for a pipeline
            without its bundle, the gappy estimates of its selected samples).
        k: (N, 8) their fault vectors.  current: (N, n_e) the records [A].
        gappy, network: the FDI's gappy layer and network (alpha [, noise] -> k_hat), for the floors.
        mean: (n_e,) POD mean [A] and modes: (n_e, n_m) POD modes; only the rows of :func:`record_stride` are read.
        nominal, seed, params: as :func:`fit_forward_check`.

    The fit's wall time [s] is ``fit_s_``; :meth:`ForwardSurrogate.summary` gives the figures phm-train reports.
    ``floor_full_`` and ``floor_samples_`` are the medians over the held-out rows of the relative residual
    (:func:`consistency_statistic` with noise 0 and floor 1) of the noise-free records at the FDI's own estimates,
    on the full-record check's rows and on the selected samples."""
    t0 = time.perf_counter()
    if nominal is not None:
        params.setdefault("nominal_eccentricity", float(nominal[ECC_AMPLITUDE]))
    model = ForwardSurrogate(int(alpha.shape[1]), seed=seed, **params)
    mean_square = torch.cat(
        [current[i : i + block_rows].to(torch.float64).pow(2).mean(1) for i in range(0, len(current), block_rows)]
    )
    model.fit(k, alpha.to(torch.float32), 1.0 / mean_square.clamp(min=1e-12))
    n_hold = max(1, round(model.holdout * len(k)))
    hold = torch.randperm(len(k), generator=torch.Generator().manual_seed(seed))[:n_hold]  # fit's own draw
    y = current[hold].to(mean.dtype)
    samples = gappy.select(y)
    a_hat, _ = gappy(samples)
    k_hat = (
        network(a_hat, torch.zeros(len(hold), dtype=a_hat.dtype))
        if getattr(network, "noise_input", False)
        else network(a_hat)
    )
    pred = model(k_hat)
    zero, one = torch.zeros(len(hold)), torch.tensor(1.0)
    rows = torch.arange(0, mean.shape[0], record_stride(int(mean.shape[0]), int(modes.shape[1])))
    full = consistency_statistic(y[:, rows], mean[rows], modes[rows], pred, zero, one)
    sel = consistency_statistic(samples, gappy.mean_hat, gappy.modes_hat, pred, zero, one)
    model.floor_full_ = full.median().to(model.floor_full_.dtype)
    model.floor_samples_ = sel.median().to(model.floor_samples_.dtype)
    model.fit_s_ = time.perf_counter() - t0
    return model.eval()
