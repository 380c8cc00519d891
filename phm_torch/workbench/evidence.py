"""Evidence for a candidate: which residual pattern its signature explains.

The part of the residual a candidate explains is e = -theta S (its one-step fitted signature). For each
physical coordinate the share of e's variance that is a function of that coordinate is the correlation
ratio eta^2 = between-bin variance / total variance (bins of equal resolution for every coordinate):

* ``speed``: signed motor speed;  ``reversal``: time from the nearest velocity reversal (both directions;
  samples far from any reversal form one bin);  ``position``: surface angle;  ``electrical_angle``: rotor
  electrical angle mod 2 pi (commutation);  ``current``: current magnitude;
* ``harmonic``: the best single mechanical harmonic h >= 2 of the rotor angle (R^2 of a cos + b sin + c),
  for patterns periodic in the rotor angle (cogging: h = slots); the envelope current is demodulated by the
  sign of the model's motor torque first (the envelope |I| flips a torque ripple with every torque reversal).

The coordinate with the largest eta^2 names the pattern; the count-weighted correlation between the binned
residual and the binned e in that coordinate says how well the candidate matches what is actually there.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from ..effects import EFFECTS
from .diagnostics import Coordinates, PerRecord, reversals

LABELS = {
    "speed": "motor speed (signed)",
    "reversal": "velocity reversals",
    "position": "surface position",
    "electrical_angle": "rotor electrical angle",
    "current": "current magnitude",
    "harmonic": "rotor mechanical angle",
}


@dataclass
class Groups:
    """Bin index of every sample (records concatenated) for each coordinate, and the harmonic basis angle."""

    index: dict[str, np.ndarray]
    counts: dict[str, int]
    angle: np.ndarray
    torque_sign: np.ndarray


def groups(
    coords: Sequence[Coordinates],
    user_angle: Sequence[np.ndarray],
    bins: int,
    pole_pairs: int,
    sample_rate: float,
    reversal_window: float,
    slots: int,
) -> Groups:
    """Bin indices (``bins`` bins per coordinate) of every sample for the evidence maps.

    The surface-position bins are never finer than one slot pitch 2 pi / ``slots`` of rotor travel: the rotor
    angle is N times the surface angle, so finer position bins would resolve rotor-angle ripple too and the
    two patterns could not be told apart.
    """
    spd = np.concatenate([k.speed for k in coords])
    cur = np.abs(np.concatenate([k.current for k in coords]))
    pos = np.concatenate(list(user_angle))
    ang = np.concatenate([k.motor_angle for k in coords])

    def uniform(x: np.ndarray, lo: float, hi: float, k: int = bins) -> np.ndarray:
        return np.clip(((x - lo) / max(hi - lo, 1e-300) * k).astype(int), 0, k - 1)

    travel = float(ang.max() - ang.min())
    pos_bins = max(3, min(bins, int(travel * slots / (2 * math.pi))))
    idx = {
        "speed": uniform(spd, float(spd.min()), float(spd.max())),
        "position": uniform(pos, float(pos.min()), float(pos.max()), pos_bins),
        "electrical_angle": uniform(np.mod(pole_pairs * ang, 2 * math.pi), 0.0, 2 * math.pi),
        "current": uniform(cur, float(cur.min()), float(cur.max())),
    }
    half = max(1, round(reversal_window * sample_rate))
    rev = []
    for k in coords:
        lag = np.full(len(k.speed), 2 * bins, dtype=int)  # far from any reversal
        top = float(np.abs(k.speed).max()) if len(k.speed) else 0.0
        for branch, ids in enumerate(reversals(k.speed, 0.02 * top)):
            for i in ids:
                lo, hi = max(i - half, 0), min(i + half + 1, len(k.speed))
                rel = np.arange(lo, hi) - i
                lag[lo:hi] = branch * bins + uniform(rel.astype(float), -half, half)
        rev.append(lag)
    idx["reversal"] = np.concatenate(rev)
    return Groups(
        idx, {k: int(v.max()) + 1 for k, v in idx.items()}, ang, np.concatenate([k.torque_sign for k in coords])
    )


def eta_squared(y: np.ndarray, index: np.ndarray, count: int) -> tuple[float, np.ndarray, np.ndarray]:
    """Correlation ratio of y on the bins, with the bin means and counts."""
    n = np.bincount(index, minlength=count).astype(np.float64)
    s = np.bincount(index, y, minlength=count)
    means = np.where(n > 0, s / np.maximum(n, 1), np.nan)
    total = float(np.sum((y - y.mean()) ** 2))
    between = float(np.nansum(n * (means - y.mean()) ** 2))
    return (between / total if total > 0 else 0.0), means, n


def harmonic_fit(y: np.ndarray, angle: np.ndarray, max_order: int) -> tuple[int, float]:
    """Best single harmonic h in 2..max_order of the rotor angle: (h, R^2)."""
    total = float(np.sum((y - y.mean()) ** 2))
    best = (0, 0.0)
    for h in range(2, max_order + 1):
        a = np.stack([np.cos(h * angle), np.sin(h * angle), np.ones_like(angle)], axis=1)
        coef, *_ = np.linalg.lstsq(a, y, rcond=None)
        r2 = 1.0 - float(np.sum((y - a @ coef) ** 2)) / total if total > 0 else 0.0
        if r2 > best[1]:
            best = (h, r2)
    return best


def weighted_corr(a: np.ndarray, b: np.ndarray, w: np.ndarray) -> float:
    """Count-weighted correlation of two binned profiles (bins empty in either are skipped)."""
    ok = np.isfinite(a) & np.isfinite(b) & (w > 0)
    if ok.sum() < 3:
        return float("nan")
    a, b, w = a[ok], b[ok], w[ok]
    a = a - np.average(a, weights=w)
    b = b - np.average(b, weights=w)
    den = math.sqrt(float(np.average(a * a, weights=w) * np.average(b * b, weights=w)))
    return float(np.average(a * b, weights=w) / den) if den > 0 else float("nan")


def evidence(
    name: str, explained: PerRecord, residual: PerRecord, grp: Groups, max_order: int, pole_pairs: int
) -> dict:
    """Evidence dict of one candidate.

    Args:
        explained: per record {channel: -theta S (n,)}, the residual part the candidate accounts for.
        residual: per record {channel: normalised residual (n,)}.
        grp: :func:`groups` of the calibrated model's trajectory.
    Returns:
        {"pattern", "share" (eta^2 of the pattern), "correlation" (binned residual vs explained part),
        "shares": {coordinate: eta^2}, "harmonic" (mechanical order of the best harmonic), "summary",
        "explains" (the effect's own description)}.
    """
    chans = list(explained[0])
    # the channel carrying most of the explained part decides the pattern
    energy = {c: sum(float(np.sum(e[c] ** 2)) for e in explained) for c in chans}
    ch = max(energy, key=energy.get)
    y = np.concatenate([e[ch] for e in explained])
    r = np.concatenate([v[ch] for v in residual])
    shares, corr = {}, {}
    for m, index in grp.index.items():
        shares[m], me, n = eta_squared(y, index, grp.counts[m])
        _, mr, _ = eta_squared(r, index, grp.counts[m])
        corr[m] = weighted_corr(mr, me, n)
    flip = grp.torque_sign if ch == "current" else 1.0  # envelope: undo the sign flips (torque ripple)
    order, r2 = harmonic_fit(y * flip, grp.angle, max_order)
    shares["harmonic"] = r2
    if order:
        a = np.stack([np.cos(order * grp.angle), np.sin(order * grp.angle), np.ones_like(grp.angle)], axis=1)
        fits = [a @ np.linalg.lstsq(a, v * flip, rcond=None)[0] for v in (r, y)]
        corr["harmonic"] = float(np.corrcoef(fits[0], fits[1])[0, 1])
    best = max(shares, key=shares.get)
    detail = (
        f", harmonic {order} per revolution ({order / pole_pairs:g} per electrical period)"
        if best == "harmonic"
        else ""
    )
    c = corr.get(best, float("nan"))
    summary = (
        f"{ch} residual pattern vs {LABELS[best]}{detail}: {100 * shares[best]:.0f} % of the effect's "
        f"signature is a function of it; binned correlation with the residual r = {c:.2f}"
    )
    return {
        "channel": ch,
        "pattern": best,
        "share": shares[best],
        "correlation": c,
        "shares": shares,
        "harmonic": order,
        "summary": summary,
        "explains": EFFECTS[name].explains if name in EFFECTS else "",
    }
