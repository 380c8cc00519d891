"""scripts/grid_density_check.py: a store's labels relabelled at another sweep density, with its own assessment."""

from __future__ import annotations

import copy
import logging

import numpy as np
import pytest
from script_module import script_module

from phm_torch.apps.generate import generate

TINY_AUTO = (  # a tiny LF store whose sweep grid is derived (auto), with 16 labels
    "dataset.fidelity=lf",
    "command.duration=0.02",
    "dataset.n_train=4",
    "dataset.n_val=1",
    "dataset.n_rul=1",
    "dataset.chunk_size=6",
    "assessment.sweep.cycles=3",
    "assessment.sweep.max_extensions=0",  # the 4-cycle reading, unless a test switches settling on
    "assessment.sweep.refine=0",
    "assessment.sweep.rotor_positions=1",  # one rest angle: these tests are about the check, not the angles
    "progress=false",
    "threads=1",
    "+dataset.healthy_fraction=null",
    "dataset.n_labels=16",
    "+dataset.label_chunk_size=8",
)


@pytest.mark.slow  # 2-4 min on 2 cores
def test_the_stores_own_density_reproduces_its_labels_and_another_is_counted(tmp_path, compose):
    data_dir = tmp_path / "store"
    generate(compose("generate", [*TINY_AUTO, f"data_dir={data_dir}"]))
    script = script_module("grid_density_check")
    same = script.check(str(data_dir), 12.0, "labels", None, 6)
    assert same["nearest_requirements"] == {"n": 6, "changed": 0}  # the labels, made again the same way
    denser = script.check(str(data_dir), 36.0, "labels", None, 6)
    assert denser["frequencies"] > 2 * same["frequencies"] and 0 <= denser["nearest_requirements"]["changed"] <= 6
    # the vectors picked are those whose measured margins lie nearest the requirements
    from phm_torch.data.store import DatasetStore

    with DatasetStore(str(data_dir)) as store:
        margins = np.asarray(store.split("labels").margins)
    dist = script.boundary_distance(
        margins, {"phase_margin_deg": 45.0, "gain_margin_db": 6.0, "bandwidth_fraction": 0.9}, 20.0
    )
    assert dist.shape == (16,) and bool((dist[~np.isnan(dist)] >= 0).all())
    with pytest.raises(ValueError, match="split 'test' is not in the store"):
        script.check(str(data_dir), 36.0, "test", None, 6)


@pytest.mark.slow  # a diagnostic script on a store; ~30 s
def test_a_listed_grid_has_no_density(tmp_path, compose):
    data_dir = tmp_path / "store"
    listed = [*TINY_AUTO, "assessment.sweep.frequencies=[15,30,60,90,130]", "assessment.sweep.group_size=5"]
    generate(compose("generate", [*listed, f"data_dir={data_dir}"]))
    with pytest.raises(ValueError, match="is a list .* it has no density"):
        script_module("grid_density_check").check(str(data_dir), 36.0, "labels", None, 4)


@pytest.mark.slow  # 2-4 min on 2 cores
def test_a_store_labelled_with_settled_refined_readings_records_them_and_is_reproduced(tmp_path, compose, caplog):
    data_dir = tmp_path / "store"
    switches = ["assessment.sweep.max_extensions=1", "assessment.sweep.refine=1", "dataset.n_labels=4"]
    with caplog.at_level(logging.INFO, logger="phm_torch.pipelines.generate.pipeline"):
        metrics, _ = generate(compose("generate", [*TINY_AUTO, *switches, f"data_dir={data_dir}"]))
    settling = metrics["assessment_settling"]
    assert settling["extended"] > 0  # 3 cycles from rest: some readings moved, and were extended
    # one line sums it up (a warning, with what to raise, above 2 % uncertain labels)
    said = [r for r in caplog.records if "labels" in r.getMessage() and "uncertain" in r.getMessage()]
    assert len(said) == 1 and f"{settling['uncertain_labels']} of {settling['vectors']} labels" in said[0].getMessage()
    many = settling["uncertain_labels"] > 0.02 * settling["vectors"]
    assert (said[0].levelno == logging.WARNING) == many and ("raise assessment.sweep" in said[0].getMessage()) == many
    from phm_torch.data.store import DatasetStore

    with DatasetStore(str(data_dir)) as store:
        sweep = store.metadata["config"]["assessment"]["sweep"]
    assert sweep["max_extensions"] == 1 and sweep["refine"] == 1  # part of the labels' provenance
    same = script_module("grid_density_check").check(str(data_dir), 12.0, "labels", None, 4, max_extensions=1, refine=1)
    assert same["nearest_requirements"]["changed"] == 0 and same["settling"]["extended"] > 0
    assert same["max_extensions"] == 1 and same["refine"] == 1


@pytest.mark.slow  # a diagnostic script on a store; ~65 s
def test_recorded_assessment_rebuilds_the_stores_phi_a_or_says_what_is_missing(tmp_path, compose):
    from phm_torch.data.store import DatasetStore, recorded_actuator, recorded_assessment

    data_dir = tmp_path / "store"
    generate(compose("generate", [*TINY_AUTO, "dataset.n_labels=4", f"data_dir={data_dir}"]))
    with DatasetStore(str(data_dir)) as store:
        metadata = store.metadata
        k, margins = np.asarray(store.split("labels").K), np.asarray(store.split("labels").margins)
    assessment, params = recorded_assessment(metadata)
    assert params == recorded_actuator(metadata) and assessment.sweep.cycles == 3
    import torch

    again = assessment(torch.as_tensor(k)).margins.stacked().numpy()
    assert np.allclose(again, margins, rtol=1e-6, equal_nan=True)  # the store's own labels, made again
    assert (assessment.sweep.max_extensions, assessment.sweep.refine) == (0, 0)  # as TINY_AUTO's config records
    # a store recording settling is rebuilt with it; one made before it was the default records neither: it was
    # labelled without them, and is rebuilt so (not with the shipped YAML's 2 and 1)
    settled = copy.deepcopy(dict(metadata))
    settled["config"]["assessment"]["sweep"].update(max_extensions=2, refine=1)
    assert (recorded_assessment(settled)[0].sweep.max_extensions, recorded_assessment(settled)[0].sweep.refine) == (
        2,
        1,
    )
    for key in ("max_extensions", "refine"):
        del settled["config"]["assessment"]["sweep"][key]
    assert (recorded_assessment(settled)[0].sweep.max_extensions, recorded_assessment(settled)[0].sweep.refine) == (
        0,
        0,
    )
    denser, _ = recorded_assessment(metadata, sweep={"cycles": 5})
    assert denser.sweep.cycles == 5 and denser.sweep.frequencies == assessment.sweep.frequencies
    no_assessment = {"config": {k: v for k, v in metadata["config"].items() if k != "assessment"}}
    with pytest.raises(ValueError, match="does not record the actuator and assessment config"):
        recorded_assessment(no_assessment)
