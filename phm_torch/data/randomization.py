"""Randomised effect strengths for the training records (``dataset.randomize``): domain randomisation.

A bench or another implementation of the datasheet differs from the simulator by small effects of unknown
size (docs/surrogates.md, "modelling differences"). Training records that carry library effects at random
strengths, drawn per record, teach the FDI to look past them. ``dataset.randomize`` maps effects to
parameter ranges, ``{effect: {param: [low, high]}}``; every ``train`` record gets its own uniform draw of
each listed parameter. The other splits (``nominal``, ``val``, ``rul``) keep the store's own model: the
``dataset.effects`` values of an effect listed there too, otherwise the effect is off (strength 0), so
that the validation figures and the nominal record describe the model the pipeline is deployed against.
Health labels are unchanged: health is a property of the fault vector.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch

from ..effects import EFFECTS, Effect, build_effects


@dataclass(frozen=True)
class RandomizedParam:
    """One randomised parameter: effect, parameter, and its uniform range [low, high] (the parameter's unit)."""

    effect: str
    param: str
    low: float
    high: float


def parse_randomization(
    randomize: Mapping[str, Any] | None, effects: Mapping[str, Mapping[str, Any]]
) -> tuple[RandomizedParam, ...]:
    """Validate ``dataset.randomize`` and flatten it (sorted by effect, then parameter).

    Raises:
        ValueError: naming the field (``dataset.randomize.<effect>.<param>``) and the offending value.
    """
    if randomize is None:
        return ()
    if not isinstance(randomize, Mapping):
        raise ValueError(f"dataset.randomize must map effect names to {{param: [low, high]}}, got {randomize!r}")
    out = []
    for name in sorted(randomize):
        ranges = randomize[name]
        if name not in EFFECTS:
            raise ValueError(f"dataset.randomize: unknown effect {name!r}; available: {sorted(EFFECTS)}")
        if not isinstance(ranges, Mapping) or not ranges:
            raise ValueError(f"dataset.randomize.{name} must map parameters to [low, high], got {ranges!r}")
        for param in sorted(ranges):
            where = f"dataset.randomize.{name}.{param}"
            if param not in EFFECTS[name].PARAMS:
                raise ValueError(f"{where}: unknown parameter; known: {sorted(EFFECTS[name].PARAMS)}")
            bounds = ranges[param]
            if (
                not isinstance(bounds, Sequence)
                or isinstance(bounds, str)
                or len(bounds) != 2
                or not all(isinstance(b, (int, float)) and not isinstance(b, bool) for b in bounds)
                or not bounds[0] <= bounds[1]
            ):
                raise ValueError(f"{where} must be [low, high] with low <= high, got {bounds!r}")
            try:  # the effect's own checks (finite, minimum) on both ends
                for b in bounds:
                    build_effects({name: {**effects.get(name, {}), param: float(b)}})
            except ValueError as e:
                raise ValueError(f"{where}: {e}") from None
            out.append(RandomizedParam(name, param, float(bounds[0]), float(bounds[1])))
        strength = EFFECTS[name].STRENGTH
        if name not in effects and not set(strength) & set(ranges):
            raise ValueError(
                f"dataset.randomize.{name}: the effect is off in the training model and none of its "
                f"strength parameters {list(strength)} is randomised, so it stays off; randomise "
                f"one of them or list the effect in dataset.effects"
            )
    return tuple(out)


def simulator_effects(
    effects: Mapping[str, Mapping[str, Any]], randomized: Sequence[RandomizedParam]
) -> dict[str, dict[str, Any]]:
    """The effect set of the signal simulator: ``effects``, plus each randomised effect not among them with
    its strength at 0 (off: the value of the records outside ``train``)."""
    out = {name: dict(values) for name, values in effects.items()}
    for name in dict.fromkeys(r.effect for r in randomized):
        if name not in out:
            out[name] = dict.fromkeys(EFFECTS[name].STRENGTH, 0.0)
    return out


def draw(randomized: Sequence[RandomizedParam], n: int, stream: np.random.SeedSequence) -> np.ndarray:
    """(n, P) uniform draws of the P randomised parameters, one row per record."""
    rng = np.random.default_rng(stream)
    low = np.array([r.low for r in randomized])
    high = np.array([r.high for r in randomized])
    return low + (high - low) * rng.random((n, len(randomized)))


def plan_values(
    randomized: Sequence[RandomizedParam], n_rows: int, train: tuple[int, int], stream: np.random.SeedSequence
) -> np.ndarray:
    """(n_rows, P) values of a plan's rows: :func:`draw` for the ``train`` rows [start, stop), NaN elsewhere."""
    values = np.full((n_rows, len(randomized)), np.nan)
    values[train[0] : train[1]] = draw(randomized, train[1] - train[0], stream)
    return values


def base_values(sim_effects: Sequence[Effect], randomized: Sequence[RandomizedParam]) -> np.ndarray:
    """(P,) the simulator's own value of each randomised parameter (that of the records outside ``train``),
    read once, before :func:`set_values` replaces them."""
    by_name = {e.name: e for e in sim_effects}
    return np.array([float(by_name[r.effect].values[r.param].reshape(-1)[0]) for r in randomized])


def set_values(
    sim_effects: Sequence[Effect],
    randomized: Sequence[RandomizedParam],
    values: np.ndarray | None,
    m: int,
    base: np.ndarray,
    batch: int,
) -> None:
    """Give each randomised parameter of the simulator's effects its per-record values, (batch,) tensors.

    Args:
        sim_effects: the simulator's effect instances (built from :func:`simulator_effects`).
        values: (m, P) the chunk's values (``Plan.effect_values``); NaN = ``base`` (records outside ``train``).
        m: records in the chunk.
        base: (P,) from :func:`base_values`.
        batch: the simulator batch (>= m); rows m.. (padding) get ``base``.
    """
    if values is None or values.shape != (m, len(randomized)):
        raise ValueError(
            f"dataset.randomize: the chunk's effect values must be ({m}, {len(randomized)}), got "
            f"{None if values is None else values.shape}"
        )
    by_name = {e.name: e for e in sim_effects}
    for j, r in enumerate(randomized):
        column = np.full(batch, base[j])
        column[: values.shape[0]] = np.where(np.isnan(values[:, j]), base[j], values[:, j])
        ref = by_name[r.effect].values[r.param]
        by_name[r.effect].values[r.param] = torch.as_tensor(column, dtype=ref.dtype, device=ref.device)
