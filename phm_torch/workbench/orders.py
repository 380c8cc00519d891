"""Rotor-angle orders the workbench looks at, from the actuator and from the data.

* From the actuator (:func:`actuator_orders`): the electrical order p, the six-step commutation order 6 p,
  the cogging order lcm(Z_s, 2 p) (= Z_s for the usual windings) and, when the datasheet declares it, the
  pinion's tooth count (the gear-mesh order). The harmonic analysis runs up to twice the highest of them
  (:func:`max_order`) and the neural closure gets them (and their low companions) as inputs
  (:func:`closure_orders`): nothing is keyed to one motor's slot count.
* From the data (:func:`residual_orders`): the strongest rotor-angle orders of the residual, found by the
  same binned harmonic fit as the report's harmonic analysis and separated by the analysis' resolution.
  They are fed to the closure and proposed as the order of the generic ``torque_ripple`` candidate, so an
  effect outside the named library is found and named by its order.

Orders are mechanical: periods per motor (rotor) turn.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence

import numpy as np

from ..params import ActuatorParams
from .diagnostics import Coordinates, PerRecord, _binned

# Library effects whose rotor-angle order the actuator fixes: {effect: key of :func:`actuator_orders`}. A
# generic ripple is not proposed at (or next to) these orders, and is tested beyond these effects.
NAMED_ORDERS = {"cogging_torque": "cogging"}


def actuator_orders(params: ActuatorParams) -> dict[str, int]:
    """The actuator's structural orders per motor turn: {"electrical", "commutation", "cogging"[, "gear_mesh"]}."""
    p, z = int(params.pole_pairs), int(params.stator_slots)
    out = {"electrical": p, "commutation": 6 * p, "cogging": math.lcm(z, 2 * p)}
    teeth = int(getattr(params, "pinion_teeth", 0) or 0)
    if teeth:
        out["gear_mesh"] = teeth
    return out


def max_order(params: ActuatorParams) -> int:
    """Highest order analysed: twice the highest structural order (48 for 24 slots and 8 poles)."""
    return 2 * max(actuator_orders(params).values())


def closure_orders(params: ActuatorParams, data_orders: Iterable[int] = ()) -> tuple[int, ...]:
    """Closure inputs: orders 1, 2, p, 2 p, the cogging order and its double, 6 p, the gear mesh, and the
    residual's own orders (``data_orders``), sorted and unique."""
    o = actuator_orders(params)
    p, cog = o["electrical"], o["cogging"]
    base = {1, 2, p, 2 * p, cog, 2 * cog, o["commutation"], *([o["gear_mesh"]] if "gear_mesh" in o else [])}
    return tuple(sorted(base | {int(h) for h in data_orders if int(h) >= 1}))


def covered_angle(coords: Sequence[Coordinates], bins: int) -> float:
    """Rotor angle covered by the records [rad] (occupied share of ``bins`` bins of theta_m mod 2 pi times 2 pi)."""
    ang = np.mod(np.concatenate([k.motor_angle for k in coords]), 2 * math.pi)
    occupied = np.unique(np.clip((ang / (2 * math.pi) * bins).astype(int), 0, bins - 1)).size
    return 2 * math.pi * occupied / bins


def order_power(values: PerRecord, coords: Sequence[Coordinates], top: int) -> np.ndarray:
    """Variance of the binned residual explained by each single order 1..top, summed over channels, (top,).

    Same binning as :func:`~phm_torch.workbench.diagnostics.harmonics` (8 top bins of theta_m mod 2 pi, the
    envelope current demodulated), so that dwell time does not weight the fit; explained variance rather
    than amplitude because over a partial turn neighbouring orders are not orthogonal.
    """
    ang = np.mod(np.concatenate([k.motor_angle for k in coords]), 2 * math.pi)
    edges = np.linspace(0.0, 2 * math.pi, 8 * top + 1)
    centres = 0.5 * (edges[1:] + edges[:-1])
    power = np.zeros(top)
    for c in values[0]:
        y = np.concatenate([k.demodulated(c, v[c]) for v, k in zip(values, coords, strict=True)])
        mean, _, cnt = _binned(ang, y, edges)
        ok = cnt > 0
        th, yb = centres[ok], mean[ok] - mean[ok].mean()
        for h in range(1, top + 1):
            a = np.stack([np.cos(h * th), np.sin(h * th), np.ones_like(th)], axis=1)
            coef = np.linalg.lstsq(a, yb, rcond=None)[0]
            power[h - 1] += float(yb @ yb - np.sum((yb - a @ coef) ** 2)) / max(len(yb), 1)
    return power


def residual_orders(
    values: PerRecord,
    coords: Sequence[Coordinates],
    top: int,
    count: int,
    exclude: Iterable[int] = (),
    min_periods: float = 2.0,
) -> list[int]:
    """The residual's ``count`` strongest rotor-angle orders, strongest first.

    Args:
        values: per record {channel: normalised residual (n,)}.  coords: the model's coordinates per record.
        top: highest order considered.  count: how many orders to return (fewer if fewer qualify).
        exclude: orders already named by a library effect: orders closer to them than the resolution are
            skipped (a ripple there is that effect's, not a new one).
        min_periods: an order must make at least this many periods over the covered rotor angle (lower
            orders are slow trends over a partial turn, e.g. a position-dependent load).
    Returns:
        Orders whose peaks are at least the resolution 2 pi / (covered angle) apart.
    """
    if count < 0 or top < 1:
        raise ValueError(f"residual_orders: count >= 0 and top >= 1 required, got {count}, {top}")
    covered = covered_angle(coords, 8 * top)
    resolution = 2 * math.pi / max(covered, 1e-9)
    lowest = math.ceil(min_periods * resolution)
    power = order_power(values, coords, top)
    excluded = [int(h) for h in exclude]
    chosen: list[int] = []
    for h in (int(i) + 1 for i in np.argsort(-power, kind="stable")):
        if len(chosen) == count:
            break
        if h < lowest or any(abs(h - e) < resolution for e in (*excluded, *chosen)):
            continue
        chosen.append(h)
    return chosen
