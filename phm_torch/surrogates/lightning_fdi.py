"""LightningModule that trains the FDI network, with Adam or Levenberg-Marquardt, optionally end to end.

* ``optimizer="adam"``: mini-batch Adam (optional cosine decay) on the weighted MSE of the network's
  pre-saturation output.
* ``optimizer="lm"``: the paper's Levenberg-Marquardt (``trainlm.py``); every training
  step is one LM epoch on the whole training set, so the dataloader must yield it as one batch (single
  device). Lightning's EarlyStopping on ``val_err_k`` plays trainlm's ``max_fail``.
* End to end (``gappy`` given): batches carry the selected samples (B, n_w) [A] and the signals' RMS
  current (B,) instead of coefficients; the training samples are corrupted by ``augment`` (noise,
  missing samples) and go through the differentiable gappy layer into the network.

Batches: ``(x, k)`` with x = alpha (B, n_m), or ``(samples, k, rms)`` end to end; k (B, 8) targets.
The loss weights are ``uniform`` or ``err_k`` (w_7 = k6, as the paper's err_k).
"""

from __future__ import annotations

from typing import Any

import lightning as L
import torch

from .augment import SignalAugment
from .fdi_mlp import FDIMLP
from .gappy_pod import GappyPOD
from .metrics import err_k_weights
from .trainlm import TrainLM

OPTIMIZERS = ("adam", "lm")
NOISE_INPUT_NEEDS = (
    "model.network.noise_input=true needs noisy training records: model.end_to_end=true with "
    "model.augment.noise > 0 (model=fdi_e2e)"
)
WEIGHTINGS = ("uniform", "err_k")


class FDIModule(L.LightningModule):
    """Trains ``network``; see the module docstring.

    Args:
        network: the :class:`FDIMLP` (input normalisation already set).
        optimizer: ``adam`` or ``lm``.
        lr, weight_decay, cosine: Adam settings (cosine: decay the rate to 0 over max_epochs).
        loss_weighting: ``uniform`` or ``err_k``.
        lm: keyword arguments of :class:`TrainLM` (mu, mu_dec, mu_inc, mu_max, min_grad, chunk).
        gappy: the gappy layer for end-to-end training (None: batches carry coefficients).
        augment: corruption of the training samples (end to end only).
    """

    def __init__(
        self,
        network: FDIMLP,
        optimizer: str = "adam",
        lr: float = 1e-3,
        weight_decay: float = 0.0,
        cosine: bool = True,
        loss_weighting: str = "err_k",
        lm: dict[str, Any] | None = None,
        gappy: GappyPOD | None = None,
        augment: SignalAugment | None = None,
    ):
        super().__init__()
        if optimizer not in OPTIMIZERS:
            raise ValueError(f"model.optimizer must be one of {list(OPTIMIZERS)}, got {optimizer!r}")
        if loss_weighting not in WEIGHTINGS:
            raise ValueError(f"model.loss_weighting must be one of {list(WEIGHTINGS)}, got {loss_weighting!r}")
        if not (lr > 0):
            raise ValueError(f"model.lr must be > 0, got {lr!r}")
        if optimizer == "lm" and network.n_members > 1:
            raise ValueError(
                f"n_members={network.n_members}: an ensemble trains with model.optimizer=adam "
                f"(LM solves for one network's weights)"
            )
        if optimizer == "lm" and gappy is not None:
            raise ValueError("model.end_to_end needs model.optimizer=adam (LM fits a fixed data set)")
        if augment is not None and gappy is None:
            raise ValueError("model.augment needs the gappy layer in the model (model.end_to_end=true)")
        if network.noise_input and (augment is None or augment.noise <= 0):
            raise ValueError(NOISE_INPUT_NEEDS)
        self.network, self.gappy, self.augment = network, gappy, augment
        self.optimizer_name, self.lr, self.weight_decay, self.cosine = optimizer, float(lr), float(weight_decay), cosine
        self.loss_weighting = loss_weighting
        # Plain values only: they identify the architecture when a checkpoint is resumed.
        self.save_hyperparameters(
            {
                "n_inputs": network.n_inputs,
                "n_hidden": network.n_hidden,
                "n_layers": network.n_layers,
                "n_members": network.n_members,
                "noise_input": network.noise_input,
                "optimizer": optimizer,
                "end_to_end": gappy is not None,
                "n_points": gappy.n_points if gappy is not None else None,
            }
        )
        if optimizer == "lm":
            self.automatic_optimization = False
            self.lm = TrainLM(network, forward_name="preactivation", **(lm or {}))

    def _weights(self, k: torch.Tensor) -> torch.Tensor:
        return err_k_weights(k) if self.loss_weighting == "err_k" else torch.ones_like(k)

    def _inputs(
        self, batch: tuple[torch.Tensor, ...], train: bool
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor | None]:
        """(alpha, k, noise) of a batch, corrupting and projecting the samples end to end; noise (B,) is the
        relative noise each record carries (zeros for clean ones), None when the network does not take it."""
        if self.gappy is None:
            return batch[0], batch[1], None
        samples, k, scale = batch
        if samples.shape[-1] != self.gappy.n_points:  # full records (model.augment.max_shift): select the samples
            shifting = train and self.augment is not None and self.augment.max_shift > 0
            samples = self.augment.select(samples, self.gappy.indices) if shifting else self.gappy.select(samples)
        noise = torch.zeros_like(scale)
        if train and self.augment is not None:
            samples, noise = self.augment.corrupt(samples, scale)
        alpha, _ = self.gappy(samples)
        return alpha, k, noise if self.network.noise_input else None

    def forward(self, alpha: torch.Tensor, noise: torch.Tensor | None = None) -> torch.Tensor:
        return self.network(alpha, noise)

    def training_step(self, batch: tuple[torch.Tensor, ...], batch_idx: int) -> torch.Tensor | None:
        alpha, k, noise = self._inputs(batch, train=True)
        w = self._weights(k)
        if self.optimizer_name == "lm":
            out = self.lm.step(alpha, k, w)
            self.log_dict(
                {"train_loss": out.perf, "lm_mu": out.mu, "lm_grad": out.grad_norm},
                prog_bar=True,
                on_step=False,
                on_epoch=True,
                batch_size=k.shape[0],
            )
            if out.stop:
                self.trainer.should_stop = True
            return None
        loss = (w * (self.network.member_preactivations(alpha, noise) - k).pow(2)).mean()  # each member on its own
        self.log("train_loss", loss, prog_bar=True, on_step=False, on_epoch=True, batch_size=k.shape[0])
        return loss

    def on_validation_epoch_start(self) -> None:
        self._val_sums = torch.zeros(3, dtype=torch.float64, device=self.device)  # sum w*d^2, sum |d|, entries

    def validation_step(self, batch: tuple[torch.Tensor, ...], batch_idx: int) -> None:
        alpha, k, noise = self._inputs(batch, train=False)
        diff = self.network(alpha, noise) - k
        self._val_sums += torch.stack(
            [
                (err_k_weights(k) * diff.pow(2)).sum(),
                diff.abs().sum(),
                torch.tensor(float(diff.numel()), device=diff.device),
            ]
        ).to(torch.float64)

    def on_validation_epoch_end(self) -> None:
        sums = self.all_gather(self._val_sums)
        sums = sums.reshape(-1, 3).sum(0)
        n = sums[2].clamp(min=1.0)
        # err_k of the whole validation set (the paper's metric) and the mean |k error|.
        self.log_dict({"val_err_k": (sums[0] / n).sqrt().float(), "val_mae": (sums[1] / n).float()}, prog_bar=True)

    def configure_optimizers(self) -> Any:
        if self.optimizer_name == "lm":
            return None
        opt = torch.optim.Adam(self.network.parameters(), lr=self.lr, weight_decay=self.weight_decay)
        if not self.cosine:
            return opt
        sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, T_max=max(int(self.trainer.max_epochs or 1), 1))
        return {"optimizer": opt, "lr_scheduler": {"scheduler": sched, "interval": "epoch"}}

    def on_save_checkpoint(self, checkpoint: dict[str, Any]) -> None:
        if self.optimizer_name == "lm":
            checkpoint["lm_mu"] = self.lm.mu

    def on_load_checkpoint(self, checkpoint: dict[str, Any]) -> None:
        saved = {
            "n_layers": 1,
            "n_members": 1,
            "noise_input": False,  # older checkpoints
            **checkpoint.get("hyper_parameters", {}),
        }
        mine = dict(self.hparams)
        diff = {k: (saved.get(k), v) for k, v in mine.items() if saved.get(k) != v}
        if diff:
            detail = ", ".join(f"{k}={a!r} in the checkpoint vs {b!r} now" for k, (a, b) in diff.items())
            raise ValueError(f"checkpoint from another configuration: {detail}")
        if self.optimizer_name == "lm" and "lm_mu" in checkpoint:
            self.lm.mu = float(checkpoint["lm_mu"])


class KeepBest(L.Callback):
    """Keeps, in memory, the network weights of the epoch with the lowest ``monitor`` (restored after fit
    without reading a checkpoint back)."""

    def __init__(self, monitor: str = "val_err_k"):
        self.monitor = monitor
        self.best = float("inf")
        self.best_epoch = -1
        self.state: dict[str, torch.Tensor] | None = None

    def on_validation_end(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        if trainer.sanity_checking:
            return
        value = trainer.callback_metrics.get(self.monitor)
        if value is not None and float(value) < self.best:
            self.best, self.best_epoch = float(value), trainer.current_epoch
            self.state = {k: v.detach().cpu().clone() for k, v in pl_module.network.state_dict().items()}

    def restore(self, module: FDIModule) -> None:
        if self.state is not None:
            module.network.load_state_dict(self.state)

    # In Lightning's checkpoints: a run resumed from one still returns the best epoch before the interruption.
    def state_dict(self) -> dict[str, Any]:
        return {"best": self.best, "best_epoch": self.best_epoch, "state": self.state}

    def load_state_dict(self, state_dict: dict[str, Any]) -> None:
        self.best, self.best_epoch = float(state_dict["best"]), int(state_dict["best_epoch"])
        self.state = state_dict["state"]
