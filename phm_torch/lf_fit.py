"""Fit the LF shape functions to the HF model (see ``physics/dc_motor.py``).

Procedure: simulate the HF test bench on the test chirp for a design set of fault vectors that
exercise the shape functions (single-phase shorts at four levels, eccentricity at two amplitudes and
four phases, mixed cases, nominal); then choose the coefficients (a_k, a_R, a_L, commutation width) that
minimise the sum over cases of the squared envelope-current discrepancy LF - HF, each case normalised
by its HF range, with batched-finite-difference Levenberg-Marquardt. The discrepancy is then reported
on an independent random set of fault vectors.
"""

from __future__ import annotations

import math
from dataclasses import fields, replace

import torch

from .command import Chirp
from .fitting import batched_levenberg_marquardt
from .params import ActuatorParams, LFShape
from .simulator import EMASimulator

COEFFICIENTS = tuple(f.name for f in fields(LFShape))
BOUNDS = {"emf_short_gain": (0.0, 2.0), "resistance_short_gain": (0.0, 2.0),
          "inductance_short_exponent": (0.0, 4.0), "commutation_width": (0.0, math.pi / 3)}


def design_faults(nominal: tuple[float, ...]) -> torch.Tensor:
    """Fault vectors used for the fit, (n, 8)."""
    cases = [list(nominal)]
    for phase in (2, 3, 4):
        for level in (0.25, 0.5, 0.75, 1.0):
            k = list(nominal)
            k[phase] = level
            cases.append(k)
    for amp in (0.5, 1.0):
        for ph in (0.0, 0.25, 0.5, 0.75):
            k = list(nominal)
            k[5], k[6] = amp, ph
            cases.append(k)
    for mix in ((0.3, 0.0, 0.6, 0.0, 0.0, 0.4, 0.2, 0.5), (0.0, 0.2, 0.0, 0.5, 0.3, 0.7, 0.8, 0.6)):
        cases.append(list(mix))
    return torch.tensor(cases, dtype=torch.float64)


def random_faults(n: int, seed: int, importance: bool) -> torch.Tensor:
    """Independent check set, (n, 8): uniform in [0, 1]^8 (k8 = 0.5), or concentrated near nominal as
    the training data are (k_i = u^8 for the damages, k7 uniform, k8 = 0.5 +- 0.5 u^8)."""
    g = torch.Generator().manual_seed(seed)
    u = torch.rand(n, 8, generator=g, dtype=torch.float64)
    if not importance:
        u[:, 7] = 0.5
        return u
    k = u ** 8
    k[:, 6] = u[:, 6]
    sign = torch.where(torch.rand(n, generator=g, dtype=torch.float64) < 0.5, -1.0, 1.0)
    k[:, 7] = 0.5 + 0.5 * sign * k[:, 7]
    return k


def discrepancy(lf: torch.Tensor, hf: torch.Tensor) -> torch.Tensor:
    """RMS(LF - HF) / range(HF) of the envelope current per case, (n,) fraction."""
    rng = hf.amax(-1) - hf.amin(-1)
    return (lf - hf).pow(2).mean(-1).sqrt() / rng


def simulate_current(params: ActuatorParams, fidelity: str, faults: torch.Tensor, command: Chirp,
                     shape: dict[str, torch.Tensor] | None = None) -> torch.Tensor:
    sim = EMASimulator(params, fidelity)
    with torch.no_grad():
        return sim.run(faults, command, command.duration, scales=shape, channels=["current"])["current"]


def fit_shapes(params: ActuatorParams, hf_current: torch.Tensor, faults: torch.Tensor, command: Chirp,
               max_iter: int = 12) -> tuple[LFShape, dict]:
    """Fit the LF shape coefficients to HF envelope currents (n, T) of ``faults`` (n, 8)."""
    n = faults.shape[0]
    rng = (hf_current.amax(-1) - hf_current.amin(-1)).unsqueeze(-1)

    def residuals(x: torch.Tensor) -> torch.Tensor:
        p = x.shape[0]
        shape = {f"lf_{name}": x[:, i].repeat_interleave(n) for i, name in enumerate(COEFFICIENTS)}
        cur = simulate_current(params, "lf", faults.repeat(p, 1), command, shape).view(p, n, -1)
        return ((cur - hf_current) / rng / math.sqrt(cur.shape[-1])).reshape(p, -1)

    x0 = torch.tensor([getattr(params.lf_shape, c) for c in COEFFICIENTS], dtype=torch.float64)
    lo = torch.tensor([BOUNDS[c][0] for c in COEFFICIENTS], dtype=torch.float64)
    hi = torch.tensor([BOUNDS[c][1] for c in COEFFICIENTS], dtype=torch.float64)
    x0 = torch.minimum(torch.maximum(x0, lo), hi)
    res = batched_levenberg_marquardt(residuals, x0, lo, hi, step=1e-3, max_iter=max_iter)
    fitted = LFShape(**{c: float(v) for c, v in zip(COEFFICIENTS, res.x)})
    std = res.covariance().diagonal().sqrt()
    return fitted, {"cost_history": res.history, "iterations": res.iterations,
                    "std": {c: float(s) for c, s in zip(COEFFICIENTS, std)}}


def evaluate(params: ActuatorParams, faults: torch.Tensor, command: Chirp, hf: torch.Tensor | None = None
             ) -> dict:
    """LF-vs-HF envelope discrepancy for ``faults``: per case and summary (fractions of HF range)."""
    hf = hf if hf is not None else simulate_current(params, "hf", faults, command)
    lf = simulate_current(params, "lf", faults, command)
    d = discrepancy(lf, hf)
    return {"per_case": d.tolist(), "mean": float(d.mean()), "median": float(d.median()), "max": float(d.max())}


def run_fit(params: ActuatorParams, command: Chirp | None = None, n_check: int = 24, seed: int = 0) -> dict:
    """Full procedure; returns a JSON-able report including the fitted coefficients."""
    command = command or Chirp()
    design = design_faults(params.nominal_faults)
    hf_design = simulate_current(params, "hf", design, command)
    before = evaluate(params, design, command, hf_design)
    fitted, info = fit_shapes(params, hf_design, design, command)
    tuned = replace(params, lf_shape=fitted)
    after = evaluate(tuned, design, command, hf_design)
    checks = {}
    for name, importance in (("importance_sampled", True), ("uniform", False)):
        k = random_faults(n_check, seed, importance)
        checks[name] = {"faults": k.tolist(), "before": evaluate(params, k, command),
                        "after": evaluate(tuned, k, command)}
    return {"fitted": {c: getattr(fitted, c) for c in COEFFICIENTS}, "fit": info,
            "design": {"before": before, "after": after, "nominal_before": before["per_case"][0],
                       "nominal_after": after["per_case"][0]},
            "random_check": checks}
