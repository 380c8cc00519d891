"""The workbench loop: calibrate, compare, locate the failure, rank the missing effects, add the best one and
watch the error fall; a neural closure when no library effect explains the residual.

Cost plan (LF, 0.5 s record, eager): a batched simulator call costs ~5 s whatever the batch up to ~100 rows,
so every stage is one call per iteration: calibration (one call per Levenberg-Marquardt iteration, trials
and their Jacobians batched), all score tests (one call), the refits of the top candidates (fitted
together, one call per iteration).
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import replace
from typing import Any

import numpy as np
import torch

from ..effects import EFFECTS
from ..params import ActuatorParams
from .bench_lines import as_json, bench_lines, without_lines
from .calibrate import Calibration, estimate_sigma, fit_models
from .candidates import Candidate, ScoreSettings, score_tests
from .closure import ClosureResult, fit_closure
from .coordinates import coordinates
from .data import Record, load_records
from .diagnostics import (
    cross_correlation,
    error_metrics,
    harmonics,
    profiles,
    spectrum,
    whiteness,
    worst_windows,
)
from .evidence import evidence, groups
from .fidelity_gap import fidelity_gap
from .model import Evaluator
from .noise import HighBandNoise
from .orders import NAMED_ORDERS, actuator_orders, closure_orders, max_order, residual_orders
from .parameters import ParameterSpace, build_space
from .result import Round, WorkbenchResult
from .settings import WorkbenchSettings

log = logging.getLogger(__name__)

DEFAULT_FREE = ("motor_inertia", "dry_friction", "k8")
DEFAULT_GROUPS = {"dry_friction": ("coulomb_friction", "static_friction")}


class Workbench:
    """Model-vs-measurement workbench.

    Args:
        params: the datasheet.  fidelity: model fidelity (``lf`` by default: ~10x faster than ``hf``).
        effects: the model's effects {name: {param: value}}.
        free: free parameters (see :func:`~phm_torch.workbench.parameters.build_space`).
        groups: named groups of datasheet fields sharing a multiplier (``None``: :data:`DEFAULT_GROUPS`).
        faults: base fault vector (default nominal).  channels: compared channels.
        settings: the loop's tunables.  noise: noise-floor estimator (strategy; default high-band PSD).
        scale_bounds: bounds of the datasheet multipliers.  device: simulation device.
        threads: intra-op threads while simulating (1: fastest for these small batched tensors; 2 threads
            measured up to 18x slower on a shared 2-core host); ``None``: torch's setting.
        actuator: the actuator's config name, for the report's provenance record.
    """

    def __init__(
        self,
        params: ActuatorParams,
        fidelity: str = "lf",
        effects: Mapping[str, Mapping | None] | None = None,
        free: Sequence[str] = DEFAULT_FREE,
        groups: Mapping[str, Sequence[str]] | None = DEFAULT_GROUPS,
        faults: Sequence[float] | None = None,
        channels: Sequence[str] = ("position", "current"),
        settings: WorkbenchSettings | None = None,
        noise: Callable[[np.ndarray, float], float] | None = None,
        scale_bounds: tuple[float, float] = (0.2, 5.0),
        device: str | torch.device = "cpu",
        threads: int | None = 1,
        actuator: str = "unnamed",
    ):
        self.params, self.fidelity, self.actuator = params, fidelity, str(actuator)
        self.effects = {k: dict(v or {}) for k, v in (effects or {}).items()}
        self.free, self.groups = list(free), dict(DEFAULT_GROUPS if groups is None else groups)
        self.faults, self.channels = faults, tuple(channels)
        if not self.channels:
            raise ValueError("channels: at least one channel to compare is required")
        self.settings = settings or WorkbenchSettings()
        self.noise = noise or HighBandNoise()
        self.scale_bounds, self.device, self.threads = scale_bounds, device, threads
        self.space()  # validate the configuration before any simulation

    # ---- building blocks ------------------------------------------------------------------------------
    @property
    def max_order(self) -> int:
        """Highest rotor-angle order analysed: ``diagnostics.max_harmonic`` or from the actuator's orders."""
        return self.settings.diagnostics.max_harmonic or max_order(self.params)

    def residual_orders(self, cal: Calibration, count: int, exclude: Sequence[int] = ()) -> list[int]:
        """The strongest rotor-angle orders of ``cal``'s residual (see :func:`~.orders.residual_orders`)."""
        return residual_orders(cal.normalised(), coordinates(cal), self.max_order, count, exclude)

    def score_settings(self, cal: Calibration) -> ScoreSettings:
        """The score settings with the residual's strongest orders as the probed ``order`` of every candidate
        that has one (``torque_ripple``), unless the grid gives it; orders the library already names (the
        cogging order) are left out."""
        sc = self.settings.score
        open_ = [n for n in self.library(cal) if "order" in EFFECTS[n].PARAMS and "order" not in sc.grid.get(n, {})]
        if not open_:
            return sc
        named = actuator_orders(self.params)
        found = self.residual_orders(cal, sc.data_orders, [named[k] for k in NAMED_ORDERS.values()])
        grid = {n: {**sc.grid.get(n, {}), "order": [float(h) for h in found]} for n in open_ if found}
        return replace(sc, grid={**sc.grid, **grid})

    def space(self, effects: Mapping[str, Mapping] | None = None, label: str = "model") -> ParameterSpace:
        """The model with ``effects`` (default the configured ones) and its free parameters."""
        effects = self.effects if effects is None else effects
        free = [f for f in self.free if "." not in f or f.split(".", 1)[0] in effects]
        extra = {n: self.settings.refit_free.get(n, EFFECTS[n].STRENGTH) for n in effects if n in EFFECTS}
        return build_space(
            self.params, free, self.groups, self.faults, effects, extra, self.scale_bounds, self.settings.fd_step, label
        )

    def load(self, paths: Any, resample: bool = False) -> list[Record]:
        return load_records(paths, self.params, self.channels, resample)

    def evaluator(self, records: Sequence[Record]) -> Evaluator:
        return Evaluator(self.params, self.fidelity, records, self.channels, self.device, self.threads)

    def calibrate(
        self, ev: Evaluator, space: ParameterSpace | None = None, sigma: Sequence[dict[str, float]] | None = None
    ) -> Calibration:
        """Fit the free parameters of ``space`` (default: the configured model)."""
        return fit_models(
            ev,
            [space or self.space()],
            [None],
            sigma,
            self.noise,
            self.settings.calibration,
            on_iteration=_progress("calibrate"),
        )[0]

    def library(self, cal: Calibration) -> list[str]:
        names = self.settings.library if self.settings.library is not None else sorted(EFFECTS)
        return [n for n in names if n not in cal.space.effects]

    def rank(self, cal: Calibration) -> list[Candidate]:
        """Score-test every library effect missing from ``cal``'s model; attach the evidence. A candidate with
        an ``order`` (``torque_ripple``) is probed at the residual's strongest orders; with none found (no
        rotor travel) it is not tested."""
        sc = self.score_settings(cal)
        names = [n for n in self.library(cal) if "order" not in EFFECTS[n].PARAMS or sc.grid.get(n, {}).get("order")]
        # a ripple of free order is tested for what it adds beyond the effects of named orders (cogging)
        given = {n: list(NAMED_ORDERS) for n in names if "order" in EFFECTS[n].PARAMS}
        cands = score_tests(cal, names, sc, given)
        ds, p = self.settings.diagnostics, self.params
        grp = groups(
            coordinates(cal),
            [s["user_angle"].numpy() for s in cal.simulated],
            2 * ds.bins,
            p.pole_pairs,
            p.sample_rate,
            ds.reversal_window,
            p.stator_slots,
        )
        normed = cal.normalised()
        for c in cands:
            if c.aliased_with is not None:
                c.evidence = {
                    "summary": f"not testable: its signature is a combination of the free parameters "
                    f"({c.aliased_with})",
                    "pattern": None,
                    "explains": EFFECTS[c.effect].explains,
                }
                continue
            if not bool(c.contribution.abs().max() > 0):
                c.evidence = {
                    "summary": "explains nothing: the residual asks for a negative strength, which this "
                    "effect cannot have",
                    "pattern": None,
                    "explains": EFFECTS[c.effect].explains,
                }
                continue
            parts = cal.evaluator.split((-c.contribution).unsqueeze(0))
            explained = [{ch: v[0].numpy() for ch, v in part.items()} for part in parts]
            c.evidence = evidence(c.effect, explained, normed, grp, self.max_order, p.pole_pairs)
        return cands

    def confirm(self, cal: Calibration, cands: list[Candidate]) -> list[Candidate]:
        """Refit the model with each of the top ``refit_top`` testable candidates (together), set their
        ΔBIC, keep ``significant`` only where the refit lowers the BIC and the residual sum of squares by
        ``score.min_gain``, and reorder best first."""
        top = [c for c in cands if c.aliased_with is None][: self.settings.refit_top]
        if top:
            spaces, starts = [], []
            for c in top:
                keys = self.settings.refit_free.get(c.effect, EFFECTS[c.effect].STRENGTH)
                sp, x0 = cal.space.with_effect(c.effect, c.start, list(keys), cal.x, self.settings.fd_step)
                spaces.append(sp)
                starts.append(x0)
            refits = fit_models(
                cal.evaluator,
                spaces,
                starts,
                cal.sigma,
                self.noise,
                self.settings.refit,
                on_iteration=_progress("refit"),
            )
            for c, rf in zip(top, refits, strict=True):
                c.refit, c.delta_bic = rf, rf.bic - cal.bic
                gain = (cal.chi2 - rf.chi2) / cal.chi2
                c.significant = c.significant and c.delta_bic < 0 and gain >= self.settings.score.min_gain
        return sorted(cands, key=_order)

    def finish(self, cal: Calibration) -> Calibration:
        """``cal``'s fit continued with the calibration's settings (the added candidate's model is calibrated
        like the configured one): the refits that confirm the candidates stop after ``refit.max_iter``, too
        few for a large effect (a trim load of a tenth of the stall torque: the friction and inertia the
        calibration had bent to absorb it come back in a few more iterations)."""
        return fit_models(
            cal.evaluator,
            [cal.space],
            [cal.x],
            cal.sigma,
            self.noise,
            self.settings.calibration,
            on_iteration=_progress("finish"),
        )[0]

    def add(self, cal: Calibration, name: str, values: Mapping[str, float] | None = None) -> Calibration:
        """Refit ``cal``'s model with effect ``name`` added (its strength and ``refit_free`` parameters free)."""
        keys = self.settings.refit_free.get(name, EFFECTS[name].STRENGTH)
        sp, x0 = cal.space.with_effect(name, dict(values or {}), list(keys), cal.x, self.settings.fd_step)
        return fit_models(
            cal.evaluator, [sp], [x0], cal.sigma, self.noise, self.settings.refit, on_iteration=_progress(f"add {name}")
        )[0]

    def fit_closure(self, cal: Calibration) -> ClosureResult:
        """Fit a neural closure on top of ``cal``'s calibrated model (frozen) and attribute it to its inputs."""
        cs = self.settings.closure
        orders = cs.harmonics or closure_orders(self.params, self.residual_orders(cal, cs.data_orders))
        return fit_closure(cal, cs, self.noise, self.fidelity, self.device, orders)

    def diagnose(self, cal: Calibration) -> dict:
        """Where ``cal`` fails: worst windows, residual maps, harmonics, spectrum, whiteness, cross-correlation."""
        ds, p = self.settings.diagnostics, self.params
        recs = cal.evaluator.records
        errors, normed = cal.errors(), cal.normalised()
        coords = coordinates(cal)
        measured = [{c: r.measured[c].numpy() for c in self.channels} for r in recs]
        return {
            "worst_windows": worst_windows(
                errors, measured, [r.name for r in recs], p.sample_rate, ds.window, ds.worst
            ),
            "profiles": profiles(normed, coords, ds, p.pole_pairs, p.sample_rate),
            "harmonics": harmonics(normed, coords, self.max_order),
            "spectrum": spectrum(errors, p.sample_rate),
            "whiteness": whiteness(normed, ds),
            "cross_correlation": cross_correlation(normed, [r.command.numpy() for r in recs], ds),
        }

    def metrics(self, cal: Calibration, sigma: Sequence[dict[str, float]]) -> dict:
        measured = [{c: r.measured[c].numpy() for c in self.channels} for r in cal.evaluator.records]
        return error_metrics(cal.errors(), measured, sigma)

    # ---- the whole loop -----------------------------------------------------------------------------
    def run(self, records: Sequence[Record]) -> WorkbenchResult:
        """Calibrate the configured model, rank the missing effects, refit the top ones, add the best (up to
        ``rounds`` times), fit a closure if needed, diagnose before and after."""
        s = self.settings
        t0, c0 = time.perf_counter(), time.process_time()
        ev = self.evaluator(records)
        model = self.calibrate(ev)
        hum = bench_lines(records, model.simulated, self.params.gear_ratio, self.max_order)
        if hum:  # the bench's, not the actuator's: calibrate again without them (bench_lines.py)
            for name, found in hum.items():
                log.warning("%s: the bench's line(s) removed: %s", name, ", ".join(line.text() for line in found))
            records = without_lines(records, hum)
            ev = self.evaluator(records)
            model = self.calibrate(ev)
        timing = {"calibrate_s": time.perf_counter() - t0}
        current, rounds = model, []
        for k in range(s.rounds):
            t1 = time.perf_counter()
            cands = self.rank(current)
            t2 = time.perf_counter()
            cands = self.confirm(current, cands)
            t3 = time.perf_counter()
            if k == 0:
                timing.update(rank_s=t2 - t1, refit_s=t3 - t2, loop_s=t3 - t0, loop_cpu_s=time.process_time() - c0)
            best = next((c for c in cands if c.significant and c.refit is not None), None)
            if best is not None and not best.refit.result.converged:
                best.refit = self.finish(best.refit)
                best.delta_bic = best.refit.bic - current.bic
            rounds.append(Round(current, cands, best.effect if best else None, best.refit if best else None))
            if best is None:
                break
            log.info("round %d: adding %s (ΔBIC %.1f)", k + 1, best.effect, best.delta_bic)
            current = best.refit
        timing.setdefault("loop_s", time.perf_counter() - t0)
        timing.setdefault("loop_cpu_s", time.process_time() - c0)
        _explain_away(rounds)
        for rnd in rounds:
            rnd.candidates.sort(key=_order)
        noise = estimate_sigma(ev, current.simulated, self.noise)
        closure, gap = None, None
        if self._wants_closure(current, rounds, noise):
            t1 = time.perf_counter()  # nothing in the library explains it: how far is the LF model from HF here?
            floor = self.metrics(current, noise)["noise_floor"]["total"]
            gap = fidelity_gap(current, floor) if s.diagnostics.fidelity_gap else None
            timing["fidelity_gap_s"] = time.perf_counter() - t1
            t1 = time.perf_counter()
            closure = self.fit_closure(current)
            timing["closure_s"] = time.perf_counter() - t1
        before_after = [model, *[r.added_model for r in rounds if r.added_model is not None]]
        if model.space.effects and s.before_after:
            t1 = time.perf_counter()
            bare = self.calibrate(ev, self.space({}, "datasheet model"), sigma=model.sigma)
            before_after.insert(0, bare)
            timing["before_s"] = time.perf_counter() - t1
        if closure is not None:
            before_after.append(closure.calibration)
        shown = list({id(c): c for c in [model, *before_after]}.values())
        diags = {c.label: self.diagnose(c) for c in shown}
        metrics = {c.label: self.metrics(c, noise) for c in shown}
        timing["total_s"] = time.perf_counter() - t0
        timing["total_cpu_s"] = time.process_time() - c0
        timing["simulator_calls"] = float(ev.calls)
        orders = {
            "actuator": actuator_orders(self.params),
            "max_order": self.max_order,
            "residual": self.residual_orders(model, max(s.score.data_orders, s.closure.data_orders, 3)),
            "closure": list(closure.harmonics) if closure is not None else None,
        }
        return WorkbenchResult(
            list(records),
            model,
            current,
            rounds,
            before_after,
            closure,
            diags,
            metrics,
            noise,
            timing,
            s,
            self.fidelity,
            self.actuator,
            orders,
            gap,
            as_json(hum),
        )

    def _wants_closure(self, cal: Calibration, rounds: list[Round], noise: list[dict[str, float]]) -> bool:
        mode = self.settings.closure.enabled
        if mode != "auto":
            return mode == "always"
        if rounds and (rounds[-1].added is not None or any(c.significant for c in rounds[-1].candidates)):
            return False  # the library still explains something (more rounds may find more)
        white = all(v["white"] for v in whiteness(cal.normalised(), self.settings.diagnostics).values())
        m = self.metrics(cal, noise)
        return not white and m["nrmse"]["total"] > self.settings.closure.ratio * m["noise_floor"]["total"]


def _explain_away(rounds: list[Round]) -> None:
    """A candidate significant in a round but not in a later one (tested against the model with the effects
    added since) is explained away by them: its significance was borrowed from their residual."""
    for k, rnd in enumerate(rounds[:-1]):
        later = {c.effect: c for c in rounds[-1].candidates}
        added = [r.added for r in rounds[k:] if r.added]
        for c in rnd.candidates:
            if c.significant and c.effect not in added and c.effect in later and not later[c.effect].significant:
                c.significant = False
                c.evidence["explained_away_by"] = added


def _order(c: Candidate) -> tuple:
    """Sort key: significant first; refitted by BIC after the refit; then by p-value."""
    refit_bic = c.refit.bic if c.refit is not None else math.inf
    return (not c.significant, c.refit is None, refit_bic, c.log10_p)


def _progress(stage: str) -> Callable[[int, list[float]], None]:
    def cb(it: int, costs: list[float]) -> None:
        log.info("%s: iteration %d, chi2/2 %s", stage, it, ", ".join(f"{c:.1f}" for c in costs))

    return cb
