"""Hidden-effect strengths defined by detectability: the effect's signature in units of the measurement noise.

The signature SNR of a synthetic case is

    SNR = sqrt(mean_c (RMS_t(y_c[with effect] - y_c[without]) / sigma_c)^2)

over the compared channels c (current, position), from noise-free simulations of the case with and without
its hidden effects (same faults, same datasheet multipliers, same command); sigma_c is the std of the noise
the case adds to channel c. It is the quantity the workbench's own metrics see per channel (NRMSE over the
noise floor = RMS error / sigma), pooled as the root-mean-square over channels as the workbench's totals
are: the datasheet model, fed data with an uncorrelated signature of SNR s, sits at sqrt(1 + s^2) x the
noise floor before any calibration (part of the signature may then be absorbed by the free parameters).
Because the SNR is measured in the actuator's own noise units, the same SNR means the same difficulty on
any actuator, whatever the absolute size of the effect's default parameters.

:func:`scale_to_snr` scales the strength parameters (``Effect.STRENGTH``) of each case's effects by a
common factor so that the signature equals a requested SNR: the signature is linear in strength for small
effects, so the factor is target / probe SNR; one re-simulation checks it and, if it is off by more than
``tolerance``, the factor is corrected once (linearly) and the SNR measured again. Shape and phase
parameters (orders, phases, Stribeck velocity) are left as given.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import replace

import numpy as np

from ..effects import EFFECTS
from ..params import ActuatorParams
from .synthetic import Case, synthesize

SNR_CHANNELS = ("current", "position")


def _clean(
    params: ActuatorParams, cases: Sequence[Case], command: object, duration: float, fidelity: str
) -> list[dict[str, np.ndarray]]:
    """Noise-free {channel: (n,)} of every case, in one batched simulation."""
    ms = synthesize(params, [replace(c, noise={}) for c in cases], command, duration, fidelity=fidelity)
    return [{"current": m.current, "position": m.position} for m in ms]


def _snr(with_: dict[str, np.ndarray], without: dict[str, np.ndarray], case: Case, channels: Sequence[str]) -> float:
    terms = []
    for ch in channels:
        sigma = float(case.noise.get(ch, 0.0))
        if not sigma > 0:
            raise ValueError(f"case.noise[{ch!r}] must be > 0 to define a signature SNR, got {sigma!r}")
        terms.append((np.sqrt(np.mean((with_[ch] - without[ch]) ** 2)) / sigma) ** 2)
    return math.sqrt(sum(terms) / len(terms))


def signature_snr(
    params: ActuatorParams,
    cases: Sequence[Case],
    command: object,
    duration: float,
    fidelity: str = "lf",
    channels: Sequence[str] = SNR_CHANNELS,
) -> list[float]:
    """Signature SNR [-] of each case's hidden effects (0 for a case without effects).

    Args:
        cases: the cases (effects, noise std per channel, faults, datasheet multipliers).
        command: callable of time or a tensor (n,) on the acquisition grid [rad].  duration: [s].
        fidelity: model that simulates the data ("lf" or "hf").
    Returns:
        one SNR per case (RMS signature / noise std, root-mean-square over ``channels``).
    """
    bare = [replace(c, effects={}) for c in cases]
    sims = _clean(params, [*cases, *bare], command, duration, fidelity)
    n = len(cases)
    return [_snr(sims[i], sims[n + i], c, channels) if c.effects else 0.0 for i, c in enumerate(cases)]


def scaled(case: Case, factor: float) -> Case:
    """``case`` with every strength parameter of its effects multiplied by ``factor`` (shape kept)."""
    effects = {}
    for name, vals in case.effects.items():
        cls = EFFECTS[name]
        full = {k: float(vals.get(k, cls.PARAMS[k].default)) for k in cls.STRENGTH}
        effects[name] = {**vals, **{k: full[k] * factor for k in cls.STRENGTH}}
    return replace(case, effects=effects)


def scale_to_snr(
    params: ActuatorParams,
    cases: Sequence[Case],
    targets: Sequence[float | None],
    command: object,
    duration: float,
    fidelity: str = "lf",
    tolerance: float = 0.2,
    channels: Sequence[str] = SNR_CHANNELS,
) -> tuple[list[Case], list[dict]]:
    """Scale each case's hidden strengths so that its signature SNR equals ``targets[i]``.

    Cases without effects, or with target ``None``, are returned unchanged. Two or three batched
    simulations in all: the probe (cases as given, and without effects), the check, and the correction of
    the cases off by more than ``tolerance`` (relative).

    Args:
        targets: (len(cases),) requested SNR [-], > 0, or ``None``.
        tolerance: relative SNR error above which the linear factor is corrected once.
    Returns:
        (scaled cases, per case {"probe_snr", "factor", "snr", "corrected"}; ``{}`` for unchanged cases).
    Raises:
        ValueError: bad lengths, targets or tolerance, or an effect whose probe signature is zero or
        whose scaled simulation is not finite.
    """
    if len(targets) != len(cases):
        raise ValueError(f"targets must have one entry per case ({len(cases)}), got {len(targets)}")
    if not tolerance > 0:
        raise ValueError(f"tolerance must be > 0, got {tolerance!r}")
    for t in targets:
        if t is not None and not (math.isfinite(t) and t > 0):
            raise ValueError(f"targets must be finite and > 0 (or None), got {t!r}")
    todo = [i for i, c in enumerate(cases) if c.effects and targets[i] is not None]
    out, info = list(cases), [{} for _ in cases]
    if not todo:
        return out, info
    n = len(todo)
    sims = _clean(
        params, [cases[i] for i in todo] + [replace(cases[i], effects={}) for i in todo], command, duration, fidelity
    )
    without = sims[n:]
    factors = {}
    for j, i in enumerate(todo):
        probe = _snr(sims[j], without[j], cases[i], channels)
        if not (math.isfinite(probe) and probe > 0):
            raise ValueError(
                f"effects {sorted(cases[i].effects)} of case {i}: probe signature SNR is {probe!r}, "
                "cannot scale it to a target"
            )
        factors[i] = targets[i] / probe
        info[i] = {"probe_snr": probe, "factor": factors[i], "corrected": False}

    def measure(idx: list[int]) -> dict[int, float]:
        got = _clean(params, [scaled(cases[i], factors[i]) for i in idx], command, duration, fidelity)
        res = {}
        for i, g in zip(idx, got):
            s = _snr(g, without[todo.index(i)], cases[i], channels)
            if not math.isfinite(s):
                raise ValueError(
                    f"effects {sorted(cases[i].effects)} of case {i}: scaled by {factors[i]:.3g} the "
                    "simulation is not finite"
                )
            res[i] = s
        return res

    snr = measure(todo)
    off = [i for i in todo if abs(snr[i] / targets[i] - 1.0) > tolerance]
    for i in off:  # one linear correction from the measured point
        factors[i] *= targets[i] / snr[i]
        info[i]["corrected"] = True
    if off:
        snr.update(measure(off))
    for i in todo:
        out[i] = scaled(cases[i], factors[i])
        info[i].update(factor=factors[i], snr=snr[i])
    return out, info
