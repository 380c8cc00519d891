"""Ranking surrogate bundles against one another on one split: err_k with paired bootstrap intervals, and
the verdicts on the estimates with the exact McNemar test.

A 500-signal val split pins err_k down only to about +/- 0.75 points (most of the squared error sits in the
few signals with several heavy faults), so two runs closer than that cannot be ranked on it. Every bundle
runs its online FDI (gappy POD of the selected samples, the network told each record's estimated noise level)
on the same records; the bootstrap resamples the same signals for every bundle, so the spread shared by two
bundles cancels in their difference; the verdicts are compared record by record (only the records one of
the two judges right count). ``scripts/rank_bundles.py`` is the command line.
"""

from __future__ import annotations

import math

import numpy as np
import torch

from ..data.store import DatasetStore, recorded_actuator
from .augment import add_noise, noise_level, rms
from .bundle import SurrogateBundle
from .metrics import bootstrap_err_k, confusion, err_k_per_signal, fault_count

BLOCK = 2000  # records read and corrupted at a time
N_BOOT = 2000
GROUPS = ("0", "1", "2", "3+")
# the nominal k0 counted from for a store that records no actuator (made before stores recorded it: the
# reference actuator's)
UNRECORDED_NOMINAL = (0.0,) * 6 + (0.5, 0.5)


def squared_errors(
    bundles: dict[str, SurrogateBundle], data_dir: str, split: str, noise: float, seed: int
) -> tuple[dict[str, torch.Tensor], torch.Tensor, dict[str, torch.Tensor], torch.Tensor]:
    """Run every bundle on every record of a store's split (``noise`` x each record's RMS current added).

    Returns:
        per bundle, the squared err_k of every record (n,) float64; each record's heavy-fault count (n,);
        per bundle, the verdict on every record (n,) bool (True = healthy); and the records' health (n,) bool.
    """
    sq: dict[str, list[torch.Tensor]] = {name: [] for name in bundles}
    verdicts: dict[str, list[torch.Tensor]] = {name: [] for name in bundles}
    counts, healthy = [], []
    gen = torch.Generator().manual_seed(seed)
    with DatasetStore(data_dir) as store:
        for bundle in bundles.values():
            bundle.check_store(store.provenance, f"store {data_dir}")
        params = recorded_actuator(store.metadata)
        k0 = params.nominal_faults if params is not None else UNRECORDED_NOMINAL
        nominal = torch.tensor(k0, dtype=torch.float64)
        view = store.split(split)  # a ValueError naming the store's splits if it has no such split
        for start in range(0, len(view), BLOCK):
            k = torch.as_tensor(np.asarray(view.K[start : start + BLOCK]), dtype=torch.float64)
            signals = torch.as_tensor(np.asarray(view.current[start : start + BLOCK]), dtype=torch.float64)
            if noise > 0:
                signals = add_noise(signals, rms(signals), noise, gen)
            level = noise_level(signals)
            counts.append(fault_count(k, nominal).clamp(max=3))
            healthy.append(torch.as_tensor(np.asarray(view.healthy[start : start + BLOCK])).bool())
            for name, bundle in bundles.items():
                k_hat = bundle.estimate(signals, level)
                sq[name].append(err_k_per_signal(k_hat, k).pow(2))
                verdicts[name].append(bundle.verdict_healthy(k_hat))
    return (
        {name: torch.cat(q) for name, q in sq.items()},
        torch.cat(counts),
        {name: torch.cat(v) for name, v in verdicts.items()},
        torch.cat(healthy),
    )


def mcnemar_p(only_a: int, only_b: int) -> float:
    """Exact two-sided McNemar p-value of ``only_a`` against ``only_b`` discordant records."""
    n = only_a + only_b
    if n == 0:
        return 1.0
    tail = sum(math.comb(n, i) for i in range(min(only_a, only_b) + 1)) / 2.0**n
    return min(1.0, 2.0 * tail)


def verdict_table(verdicts: dict[str, torch.Tensor], healthy: torch.Tensor) -> dict[str, dict[str, object]]:
    """Per bundle: the verdict's accuracy, missed-fault and false-alarm rates, and against the first bundle
    the records only one of the two judges right (``only_<first>``, ``only_this``) with the McNemar p-value.

    Args:
        verdicts: {bundle name: (n,) bool, True = healthy}, the first the reference.
        healthy: (n,) bool, the records' true health.
    """
    first = next(iter(verdicts))
    right_first = verdicts[first] == healthy
    out = {}
    for name, v in verdicts.items():
        conf = confusion(v, healthy)
        row: dict[str, object] = {k: conf[k] for k in ("accuracy", "missed_fault_rate", "false_alarm_rate")}
        if name != first:
            right = v == healthy
            a, b = int((right_first & ~right).sum()), int((right & ~right_first).sum())
            row.update({f"only_{first}": a, "only_this": b, "mcnemar_p": mcnemar_p(a, b)})
        out[name] = row
    return out


def ranking(sq: dict[str, torch.Tensor], counts: torch.Tensor, seed: int) -> dict[str, object]:
    """err_k [%], its bootstrap 95 % interval, per-group err_k and paired differences against the first bundle.

    Args:
        sq: {bundle name: (n,) squared err_k of each record}, the first the reference.
        counts: (n,) each record's heavy-fault count, clamped to 3 (the groups ``0 1 2 3+``).
        seed: seeds the bootstrap resamples (shared by every bundle: paired).
    """
    n = len(counts)
    probs = torch.tensor([0.025, 0.5, 0.975], dtype=torch.float64)
    boot = bootstrap_err_k(torch.stack(list(sq.values())), N_BOOT, seed)  # paired: shared resamples
    boot_err = {name: boot[:, i] for i, name in enumerate(sq)}
    first = next(iter(sq))
    out: dict[str, object] = {
        "n": n,
        "group_share": {g: round(float((counts == c).double().mean()), 4) for c, g in enumerate(GROUPS)},
    }
    for name, q in sq.items():
        lo, _, hi = torch.quantile(boot_err[name], probs).tolist()
        row = {
            "err_k_pct": 100 * float(q.mean().sqrt()),
            "ci95_pct": [100 * lo, 100 * hi],
            "err_k_by_heavy_faults_pct": {
                g: 100 * float(q[counts == c].mean().sqrt()) if (counts == c).any() else None
                for c, g in enumerate(GROUPS)
            },
        }
        if name != first:
            diff = torch.quantile(boot_err[name] - boot_err[first], probs).tolist()
            row[f"minus_{first}_pp"] = [100 * x for x in diff]
        out[name] = row
    return out
