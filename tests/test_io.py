"""Measurement CSV: round trip, atomic writing, and one clear ValueError per kind of bad input."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest
import torch

from phm_torch.io import Measurement, read_measurement, write_measurement

RATE = 20000.0


def table(n: int = 11, rate: float = RATE, **extra) -> dict[str, np.ndarray]:
    t = np.arange(n) / rate
    cols = {"time": t, "command": 1e-3 * np.sin(50 * t), "position": 0.9e-3 * np.sin(50 * t - 0.1), "current": 0.5 + t}
    cols.update(extra)
    return cols


def write_text(path: Path, header: str, rows: list[str]) -> Path:
    path.write_text("\n".join([header, *rows]) + "\n")
    return path


def good_rows(n: int = 5, rate: float = RATE) -> list[str]:
    return [f"{i / rate!r},0.001,0.0009,0.5" for i in range(n)]


# ---- round trip -----------------------------------------------------------------------------------
def test_round_trip_is_exact_and_keeps_extra_channels(tmp_path):
    cols = table(101, ia=np.linspace(-1, 1, 101), speed=np.full(101, 3.25))
    path = write_measurement(tmp_path / "sub" / "m.csv", cols)
    assert path.read_text().splitlines()[0] == "time,command,position,current,ia,speed"
    m = read_measurement(path, expected_rate=RATE)
    assert isinstance(m, Measurement) and len(m) == 101
    for name in ("time", "command", "position", "current", "ia", "speed"):
        np.testing.assert_array_equal(m[name], cols[name])  # repr round-trips float64 exactly
    assert list(m.extra) == ["ia", "speed"]
    assert m.sample_rate == pytest.approx(RATE, rel=1e-12)
    assert m.source_rate is None
    # and back again, from the Measurement itself
    again = read_measurement(write_measurement(tmp_path / "again.csv", m))
    np.testing.assert_array_equal(again.current, m.current)


def test_write_from_batched_tensors_selects_index_and_columns(tmp_path):
    t = torch.arange(6, dtype=torch.float64) / RATE
    batch = {
        "time": t,
        "command": torch.zeros(3, 6),
        "position": torch.arange(18.0).reshape(3, 6),
        "current": torch.ones(3, 6),
        "speed": torch.ones(3, 6),
        "user_angle": torch.ones(3, 6),
    }
    with pytest.raises(ValueError, match="index"):
        write_measurement(tmp_path / "b.csv", batch)
    path = write_measurement(tmp_path / "b.csv", batch, index=2, columns=["speed"])
    m = read_measurement(path)
    np.testing.assert_array_equal(m.position, np.arange(12.0, 18.0))
    assert list(m.extra) == ["speed"]
    with pytest.raises(ValueError, match="'bogus'"):
        write_measurement(tmp_path / "b.csv", batch, index=0, columns=["bogus"])


def test_write_is_atomic_and_validates(tmp_path):
    path = write_measurement(tmp_path / "m.csv", table())
    before = path.read_text()
    bad = table()
    bad["current"] = bad["current"].copy()
    bad["current"][3] = np.nan
    with pytest.raises(ValueError, match="'current'"):
        write_measurement(path, bad)
    missing = table()
    del missing["position"]
    with pytest.raises(ValueError, match="position"):
        write_measurement(path, missing)
    assert path.read_text() == before  # the old file is untouched
    write_measurement(path, table(21))  # replaced in one step
    assert len(path.read_text().splitlines()) == 22
    assert sorted(p.name for p in tmp_path.iterdir()) == ["m.csv"]  # no temporary file left behind


def test_quantised_timestamps_are_accepted(tmp_path):
    rate = 30000.0
    rows = [f"{i / rate:.6f},0,0,0" for i in range(300)]  # 33.333 us steps written as 33 or 34 us
    m = read_measurement(write_text(tmp_path / "q.csv", "time,command,position,current", rows), expected_rate=rate)
    assert m.sample_rate == pytest.approx(rate, rel=1e-4)


def test_columns_in_any_order_and_whitespace(tmp_path):
    path = write_text(
        tmp_path / "o.csv",
        " current , time,position,command",
        ["0.5, 0.0, 1, 2", "0.6, 0.00005, 3, 4", "0.7, 0.0001, 5, 6"],
    )
    m = read_measurement(path, expected_rate=RATE)
    np.testing.assert_array_equal(m.current, [0.5, 0.6, 0.7])
    np.testing.assert_array_equal(m.command, [2, 4, 6])


# ---- resampling -----------------------------------------------------------------------------------
def test_rate_mismatch_raises_unless_resample(tmp_path):
    cols = table(101, rate=40000.0)
    cols["position"] = 2.0 * cols["time"] + 1.0  # linear: interpolation is exact
    path = write_measurement(tmp_path / "r.csv", cols)
    with pytest.raises(ValueError, match=r"sample rate 40000 Hz .*'time'.* expected 20000 Hz"):
        read_measurement(path, expected_rate=RATE)
    m = read_measurement(path, expected_rate=RATE, resample=True)
    assert len(m) == 51 and m.sample_rate == RATE and m.source_rate == pytest.approx(40000.0)
    np.testing.assert_allclose(m.time, np.arange(51) / RATE, rtol=0, atol=1e-15)
    np.testing.assert_allclose(m.position, 2.0 * m.time + 1.0, rtol=1e-12)
    np.testing.assert_allclose(m.command, cols["command"][::2], atol=1e-15)


def test_upsampling_keeps_span(tmp_path):
    path = write_measurement(tmp_path / "u.csv", table(11, rate=10000.0))
    m = read_measurement(path, expected_rate=RATE, resample=True)
    assert len(m) == 21 and m.time[-1] == pytest.approx(1e-3)


# ---- bad input: each raises ValueError naming the field -------------------------------------------
HEADER = "time,command,position,current"
BAD_CASES = {
    "missing column": (
        "time,command,current",
        [f"{i / RATE!r},0,0" for i in range(5)],
        r"missing required column\(s\) \['position'\]",
    ),
    "duplicate column": (
        "time,command,position,current,current",
        [f"{i / RATE!r},0,0,0,0" for i in range(5)],
        r"duplicate column 'current'",
    ),
    "empty header cell": (
        "time,command,position,current,",
        [f"{i / RATE!r},0,0,0,0" for i in range(5)],
        r"header column 5 is empty",
    ),
    "non-numeric": (
        HEADER,
        [*good_rows(3), "0.00015,0.001,abc,0.5"],
        r"line 5, column 'position': non-numeric value 'abc'",
    ),
    "empty cell": (HEADER, [*good_rows(3), "0.00015,0.001,0.0009,"], r"line 5, column 'current': non-numeric"),
    "nan": (
        HEADER,
        [*good_rows(2), "0.0001,nan,0.0009,0.5", "0.00015,0,0,0"],
        r"line 4, column 'command': value 'nan' is not finite",
    ),
    "inf": (HEADER, [*good_rows(3), "0.00015,0.001,0.0009,-inf"], r"line 5, column 'current': value '-inf'"),
    "short row": (HEADER, [*good_rows(2), "0.0001,0.001,0.0009"], r"line 4 has 3 cells, the header has 4"),
    "time decreasing": (
        HEADER,
        ["0.0,0,0,0", "0.00005,0,0,0", "0.00004,0,0,0", "0.00015,0,0,0"],
        r"column 'time' is not strictly increasing at line 4",
    ),
    "time repeated": (HEADER, ["0.0,0,0,0", "0.00005,0,0,0", "0.00005,0,0,0"], r"'time' is not strictly increasing"),
    "time gap": (
        HEADER,
        [f"{t!r},0,0,0" for t in (0.0, 5e-5, 1e-4, 2e-4, 2.5e-4, 3e-4)],
        r"column 'time' is not uniformly sampled at line 5",
    ),
    "one row": (HEADER, good_rows(1), r"at least 2 data rows, got 1"),
    "header only": (HEADER, [], r"at least 2 data rows, got 0"),
}


@pytest.mark.parametrize("case", list(BAD_CASES))
def test_bad_input_raises_value_error_naming_the_field(tmp_path, case):
    header, rows, message = BAD_CASES[case]
    path = write_text(tmp_path / "bad.csv", header, rows)
    with pytest.raises(ValueError, match=message) as info:
        read_measurement(path)
    assert str(path) in str(info.value)


def test_missing_and_empty_files(tmp_path):
    with pytest.raises(ValueError, match="no such measurement file"):
        read_measurement(tmp_path / "nope.csv")
    (tmp_path / "empty.csv").write_text("\n\n")
    with pytest.raises(ValueError, match=re.escape("empty file")):
        read_measurement(tmp_path / "empty.csv")


def test_bad_expected_rate(tmp_path):
    path = write_measurement(tmp_path / "m.csv", table())
    with pytest.raises(ValueError, match="expected_rate"):
        read_measurement(path, expected_rate=-1.0)


def test_missing_ok_columns_read_empty_and_nan_cells_as_missing(tmp_path):
    rows = [*good_rows(2), "0.0001,0.001,0.0009,", "0.00015,0.001,0.0009,nan", "0.0002,0.001,0.0009,0.5"]
    path = write_text(tmp_path / "gaps.csv", HEADER, rows)
    m = read_measurement(path, missing_ok=("current",))
    assert np.isnan(m.current[2:4]).all() and np.isfinite(m.current[[0, 1, 4]]).all()
    with pytest.raises(ValueError, match=r"line 4, column 'current': non-numeric value ''"):
        read_measurement(path)  # only where the caller can drop samples
    bad = write_text(tmp_path / "bad.csv", HEADER, [*good_rows(2), "0.0001,nan,0.0009,0.5", "0.00015,0,0,inf"])
    with pytest.raises(ValueError, match=r"line 4, column 'command': value 'nan' is not finite"):
        read_measurement(bad, missing_ok=("current",))


def test_a_bench_csv_with_units_in_its_header_semicolons_and_decimal_commas(tmp_path):
    """As a bench or a spreadsheet writes it: names in any case with a unit, a byte-order mark, semicolons and
    decimal commas; every value converted to the module's units exactly (ms -> s, mrad and deg -> rad, mA -> A)."""
    rows = ["\ufeffTime [ms];Command [mrad];Position (deg);Current (mA);temperature [C]"]
    for i in range(5):
        rows.append(f"{0.05 * i:.2f};{i},5;{2 * i};{1000 + i};25".replace(".", ","))
    path = tmp_path / "bench.csv"
    path.write_text("\n".join(rows) + "\n", encoding="utf-8")
    m = read_measurement(path, expected_rate=20000.0)
    np.testing.assert_allclose(m.time, 5e-5 * np.arange(5), rtol=1e-12)
    np.testing.assert_allclose(m.command, 1e-3 * (np.arange(5) + 0.5), rtol=1e-12)
    np.testing.assert_allclose(m.position, np.deg2rad(2.0 * np.arange(5)), rtol=1e-12)
    np.testing.assert_allclose(m.current, 1.0 + 1e-3 * np.arange(5), rtol=1e-12)
    assert list(m.extra) == ["temperature [C]"] and m.sample_rate == pytest.approx(20000.0)


def test_a_linear_actuators_record_in_millimetres_is_read_in_metres(tmp_path):
    """A ball-screw bench logs its stroke in mm: the user coordinate's SI unit is then the metre."""
    path = tmp_path / "screw.csv"
    path.write_text(
        "time,command [mm],position [mm],current\n" + "".join(f"{5e-5 * i},{i},{2 * i},1\n" for i in range(4))
    )
    m = read_measurement(path, expected_rate=20000.0)
    np.testing.assert_allclose(m.command, 1e-3 * np.arange(4), rtol=1e-12)
    np.testing.assert_allclose(m.position, 2e-3 * np.arange(4), rtol=1e-12)
    path.write_text("time,command,position,current,motor_angle [mm]\n0,0,0,1,0\n5e-5,0,0,1,0\n")
    with pytest.raises(ValueError, match="unknown unit 'mm' for 'motor_angle'"):  # the motor side turns
        read_measurement(path)


def test_an_unknown_unit_and_a_time_column_in_milliseconds_are_named(tmp_path):
    path = tmp_path / "furlongs.csv"
    path.write_text("time [fortnight],command,position,current\n0,0,0,1\n1,0,0,1\n")
    with pytest.raises(ValueError, match=r"column 'time \[fortnight\]': unknown unit 'fortnight' for 'time'"):
        read_measurement(path)
    path = tmp_path / "ms.csv"
    path.write_text("time,command,position,current\n" + "".join(f"{0.05 * i},0,0,1\n" for i in range(4)))
    with pytest.raises(ValueError, match=r"\(a time column in ms\? name it 'time \[ms\]'\)"):
        read_measurement(path, expected_rate=20000.0)
    path = tmp_path / "twice.csv"
    path.write_text("Time,time [s],command,position,current\n0,0,0,0,1\n1,1,0,0,1\n")
    with pytest.raises(ValueError, match="duplicate column 'time'"):
        read_measurement(path)
