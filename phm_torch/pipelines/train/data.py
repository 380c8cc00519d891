"""The training pipeline's data and its reduction: the store's splits (checked against the requested actuator
and command), the POD of the training currents, the selected samples and the gappy layer."""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass
from typing import Any

import torch

from ... import provenance
from ...data.store import metadata_provenance
from ...drive_range import drive_bound, within_drive_range
from ...surrogates import POD, GappyPOD, rms
from ...surrogates.data import SplitData, load_store
from ...surrogates.gappy_pod import gappy_statistics
from ...surrogates.selectors.base import Selector
from .settings import TrainSettings

log = logging.getLogger(__name__)
BEYOND_WARNING = 0.2  # warn when more than this share of the training records is beyond the drive range


@dataclass
class StoreData:
    """The store's train and val splits, its time grid (n_e,) [s] and sample rate [Hz], ``info`` (manifest,
    metadata, nominal record) and the actuator/command provenance records the run uses; ``current_bound`` [A]
    the drive range (None: none) and ``inside`` (n_train,) bool, the training records within it (None: all)."""

    train: SplitData
    val: SplitData
    grid: torch.Tensor
    sample_rate: float
    info: dict[str, Any]
    provenance: dict[str, Any]
    current_bound: float | None = None
    inside: torch.Tensor | None = None

    @property
    def beyond_range(self) -> int:
        """Training records beyond the drive range (0 without one, or when they were left out of the fits)."""
        return 0 if self.inside is None else int((~self.inside).sum())


@dataclass
class Reduction:
    """The POD, the gappy layer on the selected samples (with its Bayesian statistics or None), and the selected
    samples and gappy coefficients of both splits; ``x_tr`` the FDI network's training inputs."""

    pod: POD
    gappy: GappyPOD
    statistics: dict[str, torch.Tensor] | None
    samples_tr: torch.Tensor
    samples_va: torch.Tensor
    alpha_tr: torch.Tensor
    alpha_va: torch.Tensor
    x_tr: torch.Tensor


def load_data(settings: TrainSettings, timing: dict[str, float]) -> StoreData:
    """Read the train and val splits, check the store's actuator and command against the requested ones and
    its time grid (uniform, more training signals than modes)."""
    t0 = time.perf_counter()
    data, grid, info = load_store(settings.data_dir, dict(settings.splits), dict(settings.limits))
    where = f"store {settings.data_dir}"
    recorded = metadata_provenance(info["metadata"])
    prov = {
        key: provenance.reconcile(
            recorded.get(key), settings.requested_provenance[key], key in settings.explicit_provenance, key, where
        )
        for key in provenance.KEYS
    }
    dt = torch.diff(grid)
    if not bool((dt > 0).all()) or float(dt.max() - dt.min()) > 1e-6 * float(dt.mean()):
        raise ValueError(f"store {settings.data_dir!r}: time grid is not uniform")
    if len(data["train"]) <= settings.n_modes:  # (checked again below on the records within the drive range)
        raise ValueError(
            f"n_modes={settings.n_modes} needs more than {settings.n_modes} training signals, "
            f"the store has {len(data['train'])}"
        )
    train, bound = data["train"], drive_bound(prov.get("actuator"), settings.drive_range)
    inside = None if bound is None else within_drive_range(train.current, bound)
    if inside is not None:
        beyond, fitted = int((~inside).sum()), "left out of every fit" if settings.fit_within_drive_range else "kept"
        if int(inside.sum()) <= settings.n_modes:
            raise ValueError(
                f"drive_range={settings.drive_range}: only {int(inside.sum())} training signals stay within "
                f"{bound:g} A, n_modes={settings.n_modes} needs more (raise drive_range or set it to null)"
            )
        share = beyond / len(train)
        (log.warning if share > BEYOND_WARNING else log.info)(
            "store %s: %d of %d training records (%.1f %%) exceed the drive range, %g A (drive_range %g x the "
            "current limit): not used to calibrate the out-of-distribution thresholds, %s in the fits%s",
            settings.data_dir,
            beyond,
            len(train),
            100 * share,
            bound,
            settings.drive_range,
            fitted,
            "; is current_limit the drive's limit? (drive_range=null: no drive range)"
            if share > BEYOND_WARNING
            else "",
        )
        if settings.fit_within_drive_range:
            train, inside = train.rows(inside), torch.ones(len(train) - beyond, dtype=torch.bool)
    timing["load_s"] = time.perf_counter() - t0
    return StoreData(train, data["val"], grid, 1.0 / float(dt.mean()), info, prov, bound, inside)


def fit_reduction(settings: TrainSettings, selector: Selector, data: StoreData, timing: dict[str, float]) -> Reduction:
    """POD of the training currents, the selected samples, the gappy layer and both splits' coefficients."""
    train, val = data.train, data.val
    t0 = time.perf_counter()
    pod = POD(settings.n_modes, solver=settings.pod_solver, seed=settings.seed).fit(train.current)
    timing["pod_fit_s"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    if selector.needs_snapshots:
        selector.fit(pod.modes_, data.grid, snapshots=train.current, mean=pod.mean_)
    else:
        selector.fit(pod.modes_, data.grid)
    timing["selector_fit_s"] = time.perf_counter() - t0
    statistics = None
    if settings.gappy.estimator == "bayesian":  # the rated measurement noise (eval.noise of the median RMS) joins R
        noise_std = settings.eval.noise * float(rms(train.current).median())
        statistics = gappy_statistics(train.current, pod.modes_, pod.mean_, selector.indices_, noise_std)
    gappy = GappyPOD(pod.modes_, pod.mean_, selector.indices_, ridge=settings.gappy.ridge, **(statistics or {}))
    with torch.no_grad():
        samples_tr, samples_va = gappy.select(train.current), gappy.select(val.current)
        alpha_tr, _ = gappy(samples_tr)
        alpha_va, _ = gappy(samples_va)
        x_tr = alpha_tr if settings.model.fit.inputs == "gappy" else pod(train.current)
    return Reduction(pod, gappy, statistics, samples_tr, samples_va, alpha_tr, alpha_va, x_tr)
