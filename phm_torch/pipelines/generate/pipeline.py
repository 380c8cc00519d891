"""The generation pipeline: the dataset store of the surrogates (fault vectors K, HF signals Y, health labels Phi),
resumable and shardable, and the life split beside it.

Steps: fingerprint the data-defining config and prepare the store -> calibrate the importance sampler to
``dataset.healthy_fraction`` (a pilot, cached) -> plan the rows -> compute this shard's signal chunks and labels
chunks -> merge once every chunk exists -> the life split (``dataset.life.n_actuators`` > 0, shard 0).

:func:`generate` is a plain function of :class:`~.settings.GenerateSettings` and the injected assessment
function and damage model; ``phm-generate`` (:mod:`phm_torch.apps.generate`) composes the config, calls it and
prints what it returns.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

from ... import provenance
from ...assessment import AssessmentFunction
from ...assessment.label_check import absent_fault_message, absent_faults
from ...command import time_grid
from ...data import calibration, merge
from ...data import generation as gen
from ...data.labels import LabelComputer, make_label_plan
from ...data.store import read_json
from ...prognostics.damage import DamageModel
from .life import write_life
from .records import fingerprint, store_records
from .settings import GenerateSettings

log = logging.getLogger(__name__)
# share of uncertain labels above which they are as much the sweep's reading as the actuator's: settled and refined,
# 0.7 % (reference) and 1.3 % (rudder) at paper scale; the fixed 4 cycles, ~26 % (docs/dataset.md)
UNCERTAIN_WARN = 0.02


@dataclass
class _Run:
    """The plans of a store and what this run computed of them."""

    fp: str
    sampling: dict[str, Any]
    pilot_s: float
    plan: gen.Plan
    label_plan: gen.Plan | None
    counts: dict[str, int] = field(default_factory=lambda: {"computed": 0, "reused": 0, "repaired": 0})
    label_counts: dict[str, int] = field(default_factory=lambda: {"computed": 0, "reused": 0, "repaired": 0})
    computer: gen.ChunkComputer | None = None
    labeller: LabelComputer | None = None


def generate(
    settings: GenerateSettings,
    assessment: AssessmentFunction,
    make_damage: Callable[[Sequence[float]], DamageModel] | None = None,
) -> tuple[dict[str, Any], dict[str, Any]]:
    """Generate (or resume, or merge) the dataset store of ``settings`` in ``settings.data_dir``.

    Args:
        settings: what to generate and how to run (:class:`GenerateSettings`).
        assessment: phi_a, the health label of each fault vector.
        make_damage: nominal k_0 (8,) -> the damage law of the life split (None: no ``damage`` node).

    Returns:
        ``metrics``: per split count and healthy count, wall time, throughput of this run (signals/s,
        assessment ms/vector over every vector assessed, labels/s of the labels split, all including the
        one-off compilations), signal chunks computed/reused/repaired (``chunks``) and the same for the
        labels chunks (``label_chunks``, when ``dataset.n_labels`` > 0), whether the store is complete;
        ``objects``: ``data_dir`` (Path), ``manifest`` (dict or None), ``plan``, ``label_plan`` (or None).
    """
    data_dir, spec = settings.data_dir, settings.spec
    if settings.stage == "life":
        if spec.life.n_actuators == 0:
            raise ValueError("stage=life needs dataset.life.n_actuators > 0, got 0")
        gen.check_writable(data_dir)
        life = write_life(settings, assessment, make_damage)
        return {"data_dir": str(data_dir), "stage": settings.stage, "life": life}, {"data_dir": data_dir}

    run = _plan(settings, assessment)
    t0 = time.perf_counter()
    if merge.is_complete(data_dir, run.fp) and settings.stage != "merge":
        log.info("%s already holds the finished store of this config", data_dir)
    else:
        if settings.stage in ("all", "chunks"):
            _compute(settings, assessment, run)
        _merge(settings, assessment, run)
    wall = time.perf_counter() - t0

    complete = merge.is_complete(data_dir, run.fp)
    life = None
    if spec.life.n_actuators > 0 and settings.stage != "chunks" and settings.shard_index == 0:  # one shard writes it
        life = write_life(settings, assessment, make_damage)
    manifest = read_json(data_dir / gen.MANIFEST_FILE) if complete else None
    metrics = _metrics(settings, assessment, run, complete, wall, manifest, life)
    return metrics, {"data_dir": data_dir, "manifest": manifest, "plan": run.plan, "label_plan": run.label_plan}


def _plan(settings: GenerateSettings, assessment: AssessmentFunction) -> _Run:
    """Prepare the store of this config (its fingerprint), calibrate the sampler and plan the rows."""
    spec, nominal, seed = settings.spec, settings.params.nominal_faults, settings.seed
    fp, data_cfg = fingerprint(settings.config)
    gen.prepare_store(settings.data_dir, fp, data_cfg, settings.overwrite)
    # the importance sampler calibrated to dataset.healthy_fraction (a pilot, cached in data_dir)
    sampling, pilot_s = calibration.load_or_calibrate(
        settings.data_dir, fp, lambda: calibration.calibrate_spec(spec, nominal, assessment, seed)
    )
    _log_sampling(sampling)
    plan = gen.make_plan(spec, nominal, seed, sampling)
    return _Run(fp, sampling, pilot_s, plan, make_label_plan(spec, nominal, seed, sampling))


def _log_sampling(sampling: dict) -> None:
    """Say which importance sampling the store uses, and why a healthy-fraction target was not reached."""
    target = sampling.get("healthy_fraction_target")
    if target is None:
        return
    expected, pilot = sampling.get("expected_healthy_fraction"), sampling.get("pilot_healthy_fraction")
    share = sampling.get("near_nominal_share") or 0.0
    if share:
        log.info(
            "importance sampling: %.0f %% of the radial law kept at the paper's scaling (dataset.near_nominal_share), "
            "so the store keeps vectors near nominal while the rest move out",
            100 * share,
        )
    if sampling.get("reached", True):
        log.info(
            "importance sampling: distance exponent %s for a healthy fraction of %s (the paper's scaling gave %s)",
            sampling["distance_exponent"],
            expected,
            pilot,
        )
    else:
        at_top = sampling["distance_exponent"] >= sampling.get("max_distance_exponent", float("inf"))
        if not at_top:
            why = "the actuator is faulty almost whatever the damage: check its nominal margins"
        elif share:
            why = "a larger exponent would empty the middle of the radius (the floor keeps the near-nominal vectors)"
        else:
            why = "a larger exponent would leave almost no near-nominal vectors in the store"
        log.warning(
            "importance sampling: the healthy fraction %s is not reached; distance exponent %s (its bound) gives %s "
            "(the paper's scaling: %s); %s (docs/dataset.md). Set dataset.healthy_fraction to a reachable value%s, "
            "or null for the paper's scaling",
            target,
            sampling["distance_exponent"],
            expected,
            pilot,
            why,
            " (or dataset.near_nominal_share lower)" if share else "",
        )


def _compute(settings: GenerateSettings, assessment: AssessmentFunction, run: _Run) -> None:
    """This shard's signal chunks (the simulator built at the first chunk to compute) and labels chunks."""
    s = settings

    def compute(k, effect_values=None):
        if run.computer is None:
            run.computer = gen.ChunkComputer(s.params, s.command, s.duration, s.spec, assessment, s.device)
        return run.computer(k, effect_values)

    shard = (s.shard_index, s.shard_count, s.repair, s.progress)
    run.counts = gen.compute_chunks(s.data_dir, run.plan, run.fp, compute, *shard)
    if run.label_plan is not None:
        run.labeller = LabelComputer(assessment, s.params.nominal_faults, run.label_plan.chunk_size)
        run.label_counts = gen.compute_chunks(s.data_dir, run.label_plan, run.fp, run.labeller, *shard)


def _merge(settings: GenerateSettings, assessment: AssessmentFunction, run: _Run) -> None:
    """Merge the chunks into the store (stage merge, or stage all once every chunk exists), else say which
    chunks other shards still owe."""
    plans = [p for p in (run.plan, run.label_plan) if p is not None]
    missing = {p.layout.unit: m for p in plans if (m := gen.missing_chunks(settings.data_dir, p))}
    if settings.stage == "merge" or (settings.stage == "all" and not missing):
        grid = time_grid(settings.duration, settings.params.sample_rate)
        metadata, extra = store_records(settings, assessment, run.plan, run.label_plan, run.fp, run.sampling)
        signal = (grid.numpy(), settings.command(grid).numpy())
        merge.merge(settings.data_dir, run.plan, run.fp, *signal, metadata, extra, labels=run.label_plan)
    elif missing:
        log.info(
            "chunks %s are not done yet (other shards); run with stage=merge once they are",
            "; ".join(f"{unit} {m}" for unit, m in missing.items()),
        )


def _metrics(
    settings: GenerateSettings,
    assessment: AssessmentFunction,
    run: _Run,
    complete: bool,
    wall: float,
    manifest: dict[str, Any] | None,
    life: dict[str, Any] | None,
) -> dict[str, Any]:
    """The run's metrics (see :func:`generate`), in the order ``phm-generate`` prints them."""
    prov = settings.provenance
    metrics: dict[str, Any] = {
        "data_dir": str(settings.data_dir),
        "complete": complete,
        "fingerprint": run.fp,
        "actuator": provenance.describe(prov["actuator"]),
        "command": provenance.describe(prov["command"]),
        "shard": {"index": settings.shard_index, "count": settings.shard_count},
        "stage": settings.stage,
        "chunks": {"total": run.plan.n_chunks, **run.counts},
    }
    if run.label_plan is not None:
        metrics["label_chunks"] = {"total": run.label_plan.n_chunks, **run.label_counts}
    metrics["wall_time_s"] = round(wall, 2)
    metrics["sampling"] = {**run.sampling, "pilot_s": round(run.pilot_s, 2)}
    metrics["assessment_sweep"] = {
        "frequencies": list(assessment.sweep.frequencies),
        "amplitude": assessment.sweep.amplitude,
        "auto": assessment.auto,
        "invisible_faults": assessment.invisible_faults(),
    }
    if metrics["assessment_sweep"]["invisible_faults"]:
        log.warning(
            "the health labels cannot see %s: at k = 1 it reads exactly the nominal margins (the sweep keeps the "
            "rotor in one commutation sector, where that phase does not conduct); assessment.sweep.rotor_positions=3 "
            "(the shipped value) labels the worst of three sectors (docs/dataset.md, 'Which faults the labels see')",
            ", ".join(metrics["assessment_sweep"]["invisible_faults"]),
        )
    absent = absent_faults(assessment.params)
    metrics["absent_faults"] = absent
    for name, value in absent.items():
        log.warning("%s", absent_fault_message(name, value))
    if manifest is not None:
        metrics["splits"] = {
            s: {
                "count": v["count"],
                "healthy": v["healthy"],
                "healthy_fraction": round(v["healthy"] / v["count"], 4) if v["count"] else None,
                "unmeasurable": v.get("unmeasurable"),
            }
            for s, v in manifest["splits"].items()
        }
    timing: dict[str, float] = {}
    if run.computer is not None:
        n_sig = run.counts["computed"] * settings.spec.chunk_size
        metrics["signals_per_s"] = round(n_sig / max(run.computer.timing["signals_s"], 1e-9), 2)
        timing |= run.computer.timing
    labeller = run.labeller
    if labeller is not None and labeller.vectors:  # vectors assessed for the labels split, padding included
        metrics["labels_per_s"] = round(labeller.vectors / max(labeller.timing["labels_s"], 1e-9), 2)
        timing |= labeller.timing
    if run.pilot_s:
        timing["pilot_s"] = run.pilot_s
    if life is not None:
        metrics["life"] = life
    if assessment.vectors:  # responses of this process (a resumed or sharded run counts its own)
        metrics["assessment_settling"] = settling = assessment.settling()  # uncertain_labels: docs/dataset.md
        share = settling["uncertain_labels"] / settling["vectors"]
        # a warning only where settling was asked for and did not suffice: the 4-cycle reading (the default) is
        # uncertain on ~26 % of the labels by design, the start transient deciding them the same way every time
        settling_on = assessment.sweep.max_extensions > 0
        many = share > UNCERTAIN_WARN
        advice = ""
        if many and settling_on:
            advice = (
                "; near the health boundary the labels are the sweep's reading: raise assessment.sweep.max_extensions "
                "(or cycles for a slow loop)"
            )
        elif many:
            advice = " (the 4-cycle reading; docs/dataset.md, 'Settling and refinement')"
        (log.warning if many and settling_on else log.info)(
            "assessment: %d of %d labels (%.1f %%) uncertain (the window before the last reads otherwise); %d "
            "responses extended, %d still moving after assessment.sweep.max_extensions=%d%s",
            settling["uncertain_labels"],
            settling["vectors"],
            100 * share,
            settling["extended"],
            settling["unsettled"],
            assessment.sweep.max_extensions,
            advice,
        )
    if timing and assessment.vectors:
        metrics["assessment_ms_per_vector"] = round(1000 * assessment.wall_s / assessment.vectors, 3)
        metrics["timing_s"] = {k: round(v, 2) for k, v in timing.items()}
    return metrics
