"""Keep or reject a fit of the LF shape coefficients (``phm-fit-lf``, :mod:`phm_torch.lf_fit`).

Decision rule (:func:`decide`): the fitted coefficients are kept only if, on *both* held-out sets and
for *both* channels (envelope current, position), neither the median nor the max NRMSE grows by more
than ``max_worsening`` (relative; default 0: no worsening at all), and the median current NRMSE falls
by at least ``min_gain`` (relative; default 2 %) on both sets. Otherwise the physical values are kept.
The physical values are the safe default: they follow from the winding geometry (EMF and resistance
proportional to the healthy turns, inductance to their square, instantaneous commutation), so a fit
has to earn its departure from them on vectors it has not seen.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

CHANNELS = ("current", "position")  # the channels compared, in the order of the simulated (B, 2, T) arrays


@dataclass
class Decision:
    """Which coefficients to keep: ``keep`` is ``"fitted"`` or ``"physical"``; ``reasons`` says why."""

    keep: str
    reasons: list[str]

    @property
    def accepted(self) -> bool:
        return self.keep == "fitted"


def decide(
    before: Mapping[str, Mapping[str, Mapping[str, float]]],
    after: Mapping[str, Mapping[str, Mapping[str, float]]],
    min_gain: float = 0.02,
    max_worsening: float = 0.0,
) -> Decision:
    """Apply the decision rule (module docstring) to held-out summaries ``{set: {channel: {median, max}}}``
    with the physical values (``before``) and the fitted ones (``after``)."""
    reasons, ok = [], True
    for name in before:
        for channel in CHANNELS:
            for stat in ("median", "max"):
                b, a = before[name][channel][stat], after[name][channel][stat]
                if a > b * (1.0 + max_worsening):
                    ok = False
                    reasons.append(f"{name} {channel} {stat} NRMSE worsens {100 * b:.2f} -> {100 * a:.2f} %")
        b, a = before[name]["current"]["median"], after[name]["current"]["median"]
        gain = 1.0 - a / b if b > 0 else 0.0
        if gain < min_gain:
            ok = False
            change = f"falls by {100 * gain:.1f} %" if gain > 0 else f"rises by {-100 * gain:.1f} %"
            reasons.append(
                f"{name} median current NRMSE {change} ({100 * b:.2f} -> {100 * a:.2f} %), "
                f"less than the {100 * min_gain:g} % fall required"
            )
    if ok:
        gains = ", ".join(
            f"{n} {100 * before[n]['current']['median']:.2f} -> {100 * after[n]['current']['median']:.2f} %"
            for n in before
        )
        return Decision(
            "fitted",
            [
                (
                    f"held-out median current NRMSE improves on every set ({gains}) and no "
                    f"held-out median or max worsens by more than {100 * max_worsening:g} %"
                )
            ],
        )
    return Decision("physical", reasons)
