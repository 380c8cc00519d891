"""The life split: run-to-failure histories of ``dataset.life.n_actuators`` actuators, written (or resumed) in
``<data_dir>/life`` beside the store (:mod:`phm_torch.data.life`, :mod:`phm_torch.data.life_files`)."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any

from ... import __version__
from ...assessment import AssessmentFunction
from ...data import generation as gen
from ...data import life as life_split
from ...data import life_files
from ...prognostics.damage import DamageModel
from .settings import GenerateSettings

# the life settings that only say how to run (not what is written): left out of the resume key
NOT_IN_KEY = ("n_actuators", "batch", "compile")


def write_life(
    settings: GenerateSettings,
    assessment: AssessmentFunction,
    make_damage: Callable[[Sequence[float]], DamageModel] | None,
) -> dict[str, Any]:
    """Write (or resume) the life split of ``settings.spec.life`` into ``<data_dir>/life``; returns its metrics.

    Args:
        assessment: phi_a, the healthy test of each inspection.
        make_damage: nominal k_0 (8,) -> the damage law (``damage`` node); None: the config has none (an error).
    """
    if make_damage is None:
        raise ValueError("damage: the life split needs a damage model (damage=coupled)")
    params, spec, config = settings.params, settings.spec, settings.config
    damage = make_damage(list(params.nominal_faults))
    life = spec.life
    simulate = life_split.simulator(
        params,
        spec.fidelity,
        spec.substeps,
        spec.effects,
        life.compile,
        settings.command,
        settings.duration,
        settings.device,
    )
    generator = life_split.LifeGenerator(
        life,
        damage,
        lambda k: assessment(k).healthy,
        simulate,
        gen.seed_streams(settings.seed)["life"],
        params.nominal_faults,
        spec.uniform,
        spec.label_chunk_size,
    )
    signal = {"fidelity": spec.fidelity, "substeps": spec.substeps, "effects": spec.effects}
    record = life_split.settings_record(life)
    prov = settings.provenance
    key_data = {
        "life": {k: v for k, v in record.items() if k not in NOT_IN_KEY},
        "seed": settings.seed,
        "actuator": prov["actuator"],
        "command": prov["command"],
        "damage": config.get("damage"),
        "assessment": config.get("assessment"),
        "signal": signal,
    }
    header = {
        "actuator": prov["actuator"],
        "command": prov["command"],
        "damage": config.get("damage"),
        "every_hours": float(life.every),
        "life": record,
        "seed": settings.seed,
        "signal": signal,
        "assessment": config.get("assessment"),
        "package_version": __version__,
    }
    return life_files.generate_life(
        settings.data_dir / life_files.LIFE_DIR, generator, key_data, header, settings.overwrite, settings.progress
    )
