"""What the health labels can see on an actuator: each single fault at k = 1 assessed by phi_a itself.

The design check (:mod:`~phm_torch.assessment.actuator_check`) measures the loop with a sweep of its own, a tenth
of the test command, to judge stability. The labels are read with the assessment's sweep (``conf/assessment``:
derived from the friction, usually far smaller), so what the check shows is not what the labels see. This
module runs the labels' own :class:`~phm_torch.assessment.health.AssessmentFunction` on the single faults and
reports:

* **invisible faults**: a fault at k = 1 whose label readings equal the nominal ones. The sweep's few electrical
  degrees keep the rotor in one commutation sector, so a short in the phase that does not conduct there changes
  nothing (the reference at rest at 0: phase A); ``assessment.sweep.rotor_positions=3`` (shipped) reads the worst of three
  sectors, where each phase conducts;
* **absent faults**: a fault that scales a datasheet value of 0 (no friction: k1; no play: k2) does not exist on
  the actuator (:func:`absent_faults`);
* **the play the sweep can measure**: above ``k2_play_exceeds_sweep`` the faulted play b0 (1 + 99 k2) is wider
  than the sweep amplitude and the margins become unmeasurable (labelled faulty).
"""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any

import torch
from hydra.utils import instantiate
from omegaconf import OmegaConf

from ..params import CONF_DIR, ActuatorParams
from .actuator_check import single_fault_cases
from .health import AssessmentFunction, HealthRequirements, reads_as
from .sweep import SineSweep


def label_visibility(params: ActuatorParams, sweep: SineSweep, requirements: HealthRequirements) -> dict[str, Any]:
    """JSON-able account of what phi_a (``sweep``, ``requirements``) reads of each single fault at k = 1.

    Returns:
        ``sweep``: the resolved frequencies [Hz], amplitude [rad] and rotor positions; ``cases``: {case: {healthy,
        margins}}; ``invisible``: the fault cases whose readings equal the nominal one; ``k2_play_exceeds_sweep``:
        the backlash level above which the play is wider than the sweep amplitude (None: never within [0, 1]).
    """
    phi = AssessmentFunction(params, sweep, requirements)
    cases = single_fault_cases(params.nominal_faults)
    names = list(cases)
    found = phi(torch.tensor([cases[n] for n in names], dtype=torch.float64))
    stacked = found.margins.stacked()
    nominal = stacked[names.index("nominal")]
    out_cases, invisible = {}, []
    for i, name in enumerate(names):
        row = stacked[i]
        same = bool(reads_as(row, nominal))
        if name != "nominal" and same and cases[name] != cases["nominal"]:
            invisible.append(name)
        out_cases[name] = {
            "healthy": bool(found.healthy[i]),
            **{k: round(float(v[i]), 3) for k, v in found.margins.as_dict().items()},
        }
    absent = absent_faults(params)
    amp, b0 = float(phi.sweep.amplitude), float(params.backlash)
    k2 = max(0.0, (amp / b0 - 1.0) / 99.0) if b0 > 0 else None  # b0 (1 + 99 k2) = amp; 0: already at nominal
    return {
        "sweep": {
            "frequencies": [float(f) for f in phi.sweep.frequencies],
            "amplitude": amp,
            "rotor_positions": phi.sweep.rotor_positions,
        },
        "cases": out_cases,
        "invisible": invisible,
        "absent": absent,
        "k2_play_exceeds_sweep": round(k2, 4) if k2 is not None and k2 <= 1.0 else None,
    }


def load_assessment(
    path: str | Path | None = None, rotor_positions: int | None = None
) -> tuple[SineSweep, HealthRequirements]:
    """The sweep and requirements of an assessment config YAML (``_target_`` nodes ``sweep`` and ``requirements``;
    default the shipped ``conf/assessment/frequency_response.yaml``), ``rotor_positions`` replacing the sweep's."""
    path = Path(path) if path is not None else CONF_DIR / "assessment" / "frequency_response.yaml"
    node = OmegaConf.to_container(OmegaConf.load(path), resolve=True)
    if not isinstance(node, dict) or "sweep" not in node or "requirements" not in node:
        raise ValueError(f"assessment: {str(path)!r} has no 'sweep' and 'requirements' nodes")
    sweep = instantiate(node["sweep"])
    if rotor_positions is not None:
        sweep = dataclasses.replace(sweep, rotor_positions=rotor_positions)
    return sweep, instantiate(node["requirements"])


__all__ = ["label_visibility", "load_assessment"]


def absent_faults(params: ActuatorParams) -> dict[str, str]:
    """{case: the datasheet value it scales} for the faults this actuator does not have: k = 1 multiplies its value
    (phm_torch/faults.py), and a value of 0 stays 0 (no friction: k1; no play: k2). The labels cannot see such a
    fault, and no test command can: the FDI's estimate of it is its training prior."""
    out = {}
    if not max(params.static_friction, params.coulomb_friction) > 0:
        out["k1"] = "static_friction and coulomb_friction"
    if not params.backlash > 0:
        out["k2"] = "backlash"
    return out


def absent_fault_message(name: str, value: str) -> str:
    """The one line that names an absent fault (:func:`absent_faults`), for the design check and phm-generate."""
    return (
        f"{name} scales the actuator's {value}, which is 0: this fault does not exist on it; no label or command can "
        "see it and the FDI's estimate of it is its training prior (give the datasheet's value if it has one)"
    )
