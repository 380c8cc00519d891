"""What phm-evaluate reads: the store's splits, the bundle, the actuator, the damage model and the assessment config,
each checked against the others' provenance."""

from __future__ import annotations

import logging
from types import SimpleNamespace
from typing import Any

import torch

from ... import provenance
from ...assessment_record import same_labels
from ...checks import build
from ...data.store import DatasetStore
from ...drive_range import within_drive_range
from ...params import ActuatorParams
from ...surrogates.bundle import SurrogateBundle
from .calibration import noisy, tracking_ranges
from .settings import EvaluateSettings

log = logging.getLogger(__name__)

TRAINING = "train"  # the split the near-nominal checks' calibration may add rows from (near_nominal.py)


def read_inputs(settings: EvaluateSettings) -> SimpleNamespace:
    """Everything the evaluation reads: provenance (reconciled with the config), assessment config, actuator, damage
    model, bundle, the evaluated split (k, signals, healthy), the calibration split (k, clean and noisy signals,
    healthy) and the tracking ranges of every split."""
    cal = settings.calibration
    with DatasetStore(settings.data_dir) as store:
        prov = {
            key: provenance.reconcile(
                (store.provenance or {}).get(key),
                settings.requested_provenance[key],
                key in settings.explicit,
                key,
                f"store {settings.data_dir}",
            )
            for key in provenance.KEYS
        }
        assessment = (
            dict(settings.assessment)
            if settings.assessment is not None
            else (store.metadata.get("config") or {}).get("assessment")
        )
    if assessment is None:
        raise ValueError(
            f"assessment: store {settings.data_dir} records no assessment config; choose one with "
            "assessment=frequency_response"
        )
    params = _actuator(prov["actuator"], settings.fallback_actuator)
    damage = build(dict(settings.damage), "damage", nominal=list(params.nominal_faults))
    bundle = SurrogateBundle.load(settings.bundle)
    provenance.require_same(bundle.provenance, prov, f"bundle {settings.bundle}")  # trained on a store of the same
    if same_labels(bundle.extra.get("assessment"), assessment) is False:  # its classifiers learned another boundary
        log.warning(
            "bundle %s: its classifiers learned the labels of another assessment function than the one the reference "
            "RULs are computed with here: verdicts and RUL events are judged against a boundary they did not learn",
            settings.bundle,
        )
    with DatasetStore(settings.data_dir) as store:
        view = store.split(settings.split)
        k = torch.as_tensor(view.K[()], dtype=torch.float64)
        signals = torch.as_tensor(view.current[()], dtype=torch.float64)
        band_view = store.split(cal.split)
        band_k = torch.as_tensor(band_view.K[()], dtype=torch.float64)
        band_clean = torch.as_tensor(band_view.current[()], dtype=torch.float64)
        band_healthy = torch.as_tensor(band_view.healthy[()]).bool()
        healthy = torch.as_tensor(view.healthy[()]).bool()
        tracking, tracking_healthy = tracking_ranges(store)
        training_k = (
            torch.as_tensor(store.split(TRAINING).K[()], dtype=torch.float64) if TRAINING in store.splits else None
        )
    if k.shape[0] == 0:
        raise ValueError(f"split {settings.split!r} of {settings.data_dir} is empty")
    bound = bundle.extra.get("drive_current_bound")
    inside = within_drive_range(band_clean, bound)
    band_k, band_clean, band_healthy = band_k[inside], band_clean[inside], band_healthy[inside]
    band_signals = noisy(band_clean, cal.noise, settings.seed)
    return SimpleNamespace(
        band_beyond_drive_range=int((~inside).sum()),
        prov=prov,
        assessment=assessment,
        params=params,
        damage=damage,
        bundle=bundle,
        k=k,
        signals=signals,
        healthy=healthy,
        band_k=band_k,
        band_clean=band_clean,
        band_signals=band_signals,
        band_healthy=band_healthy,
        tracking=tracking,
        tracking_healthy=tracking_healthy,
        training_k=training_k,
        read_training=lambda rows: _read_rows(settings.data_dir, TRAINING, rows),
    )


def _read_rows(data_dir: str, split: str, rows: list[int]) -> torch.Tensor:
    """The clean current records (len(rows), n_full) [A] of a store's split at sorted row indices."""
    with DatasetStore(data_dir) as store:
        return torch.as_tensor(store.split(split).current[rows], dtype=torch.float64)


def _actuator(record: Any, fallback: ActuatorParams | None) -> ActuatorParams:
    """The actuator of a provenance record, or the configured one for a store that records none."""
    if record is not None:
        return ActuatorParams.from_mapping(record["values"])
    if fallback is None:
        raise ValueError("actuator: the artefact records no actuator; choose one with actuator=<name>")
    return fallback
