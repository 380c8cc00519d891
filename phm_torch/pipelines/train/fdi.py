"""The FDI network's fit: built from the training inputs' scaling, trained by a Lightning Trainer (LM or Adam,
optionally end to end), its epoch chosen on training signals held out from the fit."""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import lightning as L
import torch
from torch.utils.data import DataLoader, TensorDataset

from ...surrogates import build_fdi_network, rms
from ...surrogates.augment import shifted_samples
from ...surrogates.lightning_fdi import FDIModule, KeepBest
from .data import Reduction, StoreData
from .settings import TrainSettings


@dataclass
class FDIFit:
    """The fitted FDI network (float32, eval mode), its Lightning module and trainer, the best-epoch keeper,
    and the training rows that fitted it and those that chose its epoch (None: val chose it)."""

    network: Any
    module: FDIModule
    trainer: L.Trainer
    keep: KeepBest
    fit_rows: torch.Tensor
    monitor_rows: torch.Tensor | None


def make_loggers(names: tuple[str, ...], out_dir: Any) -> list[Any]:
    """Lightning loggers by name (``csv``, ``tensorboard``) writing under ``out_dir``."""
    out: list[Any] = []
    if "csv" in names:
        out.append(L.pytorch.loggers.CSVLogger(out_dir, name="logs"))
    if "tensorboard" in names:
        try:
            out.append(L.pytorch.loggers.TensorBoardLogger(out_dir, name="tensorboard"))
        except ModuleNotFoundError as e:
            raise ValueError(
                f"loggers: tensorboard needs the tensorboard package (pip install -e '.[tensorboard]'): {e}"
            ) from None
    return out


def monitor_rows(n: int, fraction: float, seed: int) -> tuple[torch.Tensor, torch.Tensor | None]:
    """Rows of the training split that fit the FDI network and rows held out to choose its epoch.

    The epoch (early stopping, best weights) is chosen on signals the network never trains on and
    that are not the reported ``val`` split, so the ``val`` figures are not tuned on (MATLAB's trainlm
    divides its data the same way). ``fraction = 0`` keeps every row for fitting and returns ``None``:
    the epoch is then chosen on ``val`` itself (optimistic by a few tenths of a point of err_k).
    """
    if fraction == 0.0:
        return torch.arange(n), None
    n_monitor = max(1, round(fraction * n))
    if n - n_monitor < 2:
        raise ValueError(f"monitor_fraction={fraction} leaves {n - n_monitor} of {n} training signals to fit")
    perm = torch.randperm(n, generator=torch.Generator().manual_seed(seed + 0x3011))
    return perm[n_monitor:].sort().values, perm[:n_monitor].sort().values


def shifted_copies(
    fitted: list[torch.Tensor], records: torch.Tensor, red: Reduction, fit: Any, seed: int
) -> list[torch.Tensor]:
    """The fitting inputs and targets ``fitted`` [(B, n_in), (B, 8)] with ``fit.shifted_copies`` more copies of the
    records (B, n_e) behind them, each read moved by its own random shift within +- ``fit.max_shift`` samples (the
    end values held) and reduced as the inputs are (gappy coefficients of the selected samples, or the full
    projection): a network fitted on them reads a trigger that far off as on time (docs/surrogates.md)."""
    gen = torch.Generator().manual_seed(seed + 0x5A1F)
    inputs, targets = [fitted[0]], [fitted[1]]
    with torch.no_grad():
        for _ in range(fit.shifted_copies):
            shift = torch.randint(-fit.max_shift, fit.max_shift + 1, (records.shape[0], 1), generator=gen)
            if fit.inputs == "gappy":
                reduced = red.gappy(shifted_samples(records, red.gappy.indices, shift))[0]
            else:
                reduced = red.pod(shifted_samples(records, torch.arange(records.shape[1]), shift))
            inputs.append(reduced.to(fitted[0].dtype))
            targets.append(fitted[1])
    return [torch.cat(inputs), torch.cat(targets)]


def fit_fdi(
    settings: TrainSettings, data: StoreData, red: Reduction, loggers: list[Any], timing: dict[str, float]
) -> FDIFit:
    """Build the FDI network (its input scaling from the fitting rows) and train it with a Lightning Trainer,
    choosing the epoch on the monitor rows; checkpoints under ``out_dir/checkpoints``."""
    model, fit, seed, train = settings.model, settings.model.fit, settings.seed, data.train
    fit_rows, held_out = monitor_rows(len(train), settings.monitor_fraction, seed)
    network_kwargs = model.network_settings(settings.eval.noise)
    levels = None
    if network_kwargs.get("noise_input"):  # told each record's noise level, trained on levels in [0, augment.noise]
        levels = (
            torch.rand(len(fit_rows), generator=torch.Generator().manual_seed(seed + 3), dtype=red.x_tr.dtype)
            * model.max_noise
        )
    network = build_fdi_network(
        settings.n_modes, settings.n_hidden, settings.n_layers, settings.n_members, **network_kwargs
    )
    network.set_normalization(red.x_tr[fit_rows], levels)
    module = model.build(network, red.gappy)
    if module.optimizer_name == "lm":
        if fit.batch_size is not None:
            raise ValueError("model.fit.batch_size must be null for model.optimizer=lm (one full-batch step per epoch)")
        if int(settings.trainer["devices"]) != 1 or int(settings.trainer["num_nodes"]) != 1:
            raise ValueError("model.optimizer=lm runs on one device: set trainer.devices=1 and trainer.num_nodes=1")
    if model.end_to_end:
        augment = getattr(module, "augment", None)
        # shifted training records need the whole record: the module selects their samples (lightning_fdi.py)
        inputs = train.current if augment is not None and augment.max_shift > 0 else red.samples_tr
        tensors_tr = monitor_src = (inputs, train.k, rms(train.current))
        tensors_va = (red.samples_va, data.val.k, rms(data.val.current))
    else:  # monitored on gappy coefficients, as val is, whatever fit.inputs
        tensors_tr, monitor_src = (red.x_tr, train.k), (red.alpha_tr, train.k)
        tensors_va = (red.alpha_va, data.val.k)
    fitted = [t[fit_rows] for t in tensors_tr]
    if not model.end_to_end and fit.shifted_copies:
        fitted = shifted_copies(fitted, train.current[fit_rows], red, fit, seed)
    ds_tr = TensorDataset(*fitted)
    ds_va = TensorDataset(*(tensors_va if held_out is None else [t[held_out] for t in monitor_src]))
    gen = torch.Generator().manual_seed(seed)
    batch = fit.batch_size or len(ds_tr)
    train_loader = DataLoader(ds_tr, batch_size=batch, shuffle=batch < len(ds_tr), generator=gen)
    val_loader = DataLoader(ds_va, batch_size=max(len(ds_va), 1))
    keep = KeepBest("val_err_k")
    callbacks = [
        keep,
        L.pytorch.callbacks.EarlyStopping("val_err_k", patience=fit.patience, mode="min"),
        L.pytorch.callbacks.ModelCheckpoint(
            settings.out_dir / "checkpoints",
            monitor="val_err_k",
            mode="min",
            save_last=True,
            filename="fdi-{epoch:04d}-{val_err_k:.5f}",
        ),
    ]
    try:
        trainer = L.Trainer(
            max_epochs=fit.max_epochs,
            logger=loggers or False,
            callbacks=callbacks,
            default_root_dir=settings.out_dir,
            log_every_n_steps=1,
            enable_model_summary=False,
            **settings.trainer,
        )
    except (TypeError, ValueError, RuntimeError) as e:
        raise ValueError(f"trainer: {e}") from None
    ckpt = settings.ckpt_path
    if ckpt is not None and not Path(ckpt).is_file():
        raise ValueError(f"ckpt_path {ckpt!r} does not exist")
    t0 = time.perf_counter()
    trainer.fit(module, train_loader, val_loader, ckpt_path=ckpt, weights_only=True)
    timing["fdi_train_s"] = time.perf_counter() - t0
    if trainer.is_global_zero:  # the other ranks of a multi-device run stop here
        keep.restore(module)
        module.cpu()  # the gappy layer too (it is a submodule end to end)
        module.network.float().eval()
    return FDIFit(module.network, module, trainer, keep, fit_rows, held_out)
