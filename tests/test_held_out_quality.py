"""The verdict's held-out error rates: measured by phm-evaluate, carried by the exported file, given by phm-predict
beside each verdict and warned of once per run above 10 %."""

from __future__ import annotations

import json
import logging
import zipfile

import pytest
import torch

from phm_torch.online.export import METADATA_FILE, read_metadata
from phm_torch.online.quality import quality_warnings, verdict_error
from phm_torch.params import CONF_DIR
from phm_torch.pipelines.evaluate.quality import held_out_quality

PIPELINE = CONF_DIR.parent / "pretrained" / "online_surrogates_best.pt"


class ScoreOf(torch.nn.Module):
    """A pipeline stand-in: the record's first sample is its health score, its second > 0 marks it out of
    distribution."""

    def __init__(self) -> None:
        super().__init__()
        self.times = torch.zeros(2, dtype=torch.float64)

    def forward(self, x: torch.Tensor):
        return x, x[:, 0], x, x[:, 1] > 0, x[:, 0]


def test_rates_are_counted_on_answered_records_per_true_class():
    # truth: 4 faulty (one answered healthy, one out of distribution), 3 healthy (one answered faulty)
    score = [-1.0, -2.0, 0.5, -1.0, 1.0, 2.0, -0.5]
    ood = [0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0]
    healthy = torch.tensor([False, False, False, False, True, True, True])
    signals = torch.tensor([score, ood], dtype=torch.float64).T
    rul = {"rul_vectors": 5, "rul_err_median_full_flow": 0.4, "rul_band_coverage_full_flow": float("nan")}
    q = held_out_quality(ScoreOf(), signals, healthy, "val", rul)
    assert q["records"] == 7 and q["out_of_distribution"] == pytest.approx(1 / 7)
    assert (q["faulty_records"], q["healthy_records"]) == (3, 3)
    assert q["missed_faulty"] == pytest.approx(1 / 3) and q["false_alarm"] == pytest.approx(1 / 3)
    assert q["accuracy"] == pytest.approx(4 / 6)
    # NaN is no JSON: a figure not measured is null; one not given too
    assert q["rul_band_coverage_full_flow"] is None and q["rul_uncertainty_median_full_flow"] is None
    assert json.loads(json.dumps(q, allow_nan=False)) == q
    # a class absent: its rate is unknown, not 0
    none_faulty = held_out_quality(ScoreOf(), signals[4:], healthy[4:], "val", {})
    assert none_faulty["missed_faulty"] is None and none_faulty["false_alarm"] == pytest.approx(1 / 3)
    with pytest.raises(ValueError, match="signals hold 7 records, healthy 3"):
        held_out_quality(ScoreOf(), signals, healthy[:3], "val", {})


def test_each_verdict_reads_the_rate_of_its_own_kind_and_the_run_warns_above_ten_percent():
    quality = {"split": "val", "records": 100, "missed_faulty": 0.18, "false_alarm": 0.05}
    assert verdict_error(quality, healthy=True) == 0.18 and verdict_error(quality, healthy=False) == 0.05
    assert verdict_error(None, healthy=True) is None
    (line,) = quality_warnings(quality)
    assert "18 % of the faulty ones healthy" in line and "100 held-out records (val)" in line
    assert quality_warnings({**quality, "missed_faulty": 0.1}) == []  # at the threshold: said in each record only
    assert quality_warnings(None) == []
    # a RUL band that missed most reference RULs is warned of; a wide one that covers is not
    (rul,) = quality_warnings({"rul_vectors": 30, "rul_band_coverage_full_flow": 0.4})
    assert "covered 40 % of the reference RULs of 30 evaluated records" in rul
    assert quality_warnings({"rul_band_coverage_full_flow": 1.0, "rul_uncertainty_median_full_flow": 27.0}) == []


def _with_quality(path, quality):
    """The shipped pipeline file with ``held_out_quality`` in its metadata replaced (None: removed)."""
    metadata = read_metadata(PIPELINE)
    metadata.pop("held_out_quality", None)
    if quality is not None:
        metadata["held_out_quality"] = quality
    with zipfile.ZipFile(PIPELINE) as src, zipfile.ZipFile(path, "w") as dst:
        for item in src.infolist():
            data = src.read(item.filename)
            if item.filename.endswith(f"/extra/{METADATA_FILE}"):
                data = json.dumps(metadata, sort_keys=True).encode()
            dst.writestr(item, data)
    return path


@pytest.mark.torchscript
def test_phm_predict_gives_each_verdict_its_held_out_error(compose, tmp_path, caplog):
    """The pretrained pipeline with held-out figures added to its metadata, on the nominal record it carries."""
    from phm_torch.apps.predict import predict

    shipped = read_metadata(PIPELINE)
    path = _with_quality(tmp_path / "with_quality.pt", {"split": "val", "records": 500, "missed_faulty": 0.25})
    model = torch.jit.load(str(path))
    n = model.nominal_record.shape[-1]
    t = torch.arange(n, dtype=torch.float64) / 20000.0
    csv = tmp_path / "nominal.csv"
    rows = "\n".join(f"{a:.6f},{b:.9g}" for a, b in zip(t.tolist(), model.nominal_record.double().tolist()))
    csv.write_text("time,current\n" + rows + "\n")  # a current-only record: the command checks are skipped
    with caplog.at_level(logging.WARNING):
        metrics, out = predict(compose("predict", [f"pipeline={path}", f"measurements=[{csv}]"]))
    (record,) = out["records"]
    assert record["healthy"] and record["verdict_held_out_error"] == 0.25
    assert metrics["held_out_quality"]["missed_faulty"] == 0.25
    assert sum("25 % of the faulty ones healthy" in r.getMessage() for r in caplog.records) == 1
    # the shipped file carries its own figures (scripts/add_held_out_quality.py): 1.2 % of 1,392 faulty records of a
    # fresh store answered healthy, said in the record, below the warning
    caplog.clear()
    with caplog.at_level(logging.WARNING):
        _, shipped_out = predict(compose("predict", [f"pipeline={PIPELINE}", f"measurements=[{csv}]"]))
    missed = shipped["held_out_quality"]["missed_faulty"]
    assert shipped_out["records"][0]["verdict_held_out_error"] == missed and 0.0 < missed < 0.05
    assert not any("of the faulty ones healthy" in r.getMessage() for r in caplog.records)
    # a file exported before the measurement: nothing said, nothing made up
    bare = _with_quality(tmp_path / "bare.pt", None)
    _, plain = predict(compose("predict", [f"pipeline={bare}", f"measurements=[{csv}]"]))
    assert plain["records"][0]["verdict_held_out_error"] is None
