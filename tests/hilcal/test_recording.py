"""The recording CSV contract: exact round trip and one test per validation rule (line and column named)."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from structlog.testing import capture_logs

from hilcal.recording import (
    REQUIRED_COLUMNS,
    Recording,
    RecordingError,
    read_recording,
    recording_from_arrays,
    write_recording,
)
from hilcal.robot import default_robot

HEADER = (
    "seq,phase,time_s,cmd_x_mm,cmd_y_mm,cmd_z_mm,cmd_roll_deg,cmd_pitch_deg,cmd_yaw_deg,"
    "leg1_mm,leg2_mm,leg3_mm,leg4_mm,leg5_mm,leg6_mm,"
    "meas_x_mm,meas_y_mm,meas_z_mm,meas_roll_deg,meas_pitch_deg,meas_yaw_deg,temp_c,note"
)
COLS = HEADER.split(",")


def row_cells(i: int, phase: str = "measure") -> list[str]:
    """A plausible row for the paper robot: seq i, near the home pose."""
    return [
        str(i),
        phase,
        f"{1.5 * i}",
        "10.0", "-20.0", "3100.0", "1.0", "-0.5", "2.0",
        "4300.0", "4300.5", "4301.0", "4299.5", "4299.0", "4302.0",
        f"{10.0 + 0.01 * i}", "-20.02", "3100.3", "1.01", "-0.49", "2.02",
        "20.5", f"pose-{i}",
    ]  # fmt: skip


def base_rows(n_measure: int = 10, n_verify: int = 2) -> list[list[str]]:
    measure = [row_cells(i, "measure") for i in range(n_measure)]
    return [*measure, *(row_cells(n_measure + i, "verify") for i in range(n_verify))]


def set_cell(rows: list[list[str]], row: int, column: str, value: str) -> list[list[str]]:
    rows[row][COLS.index(column)] = value
    return rows


def write_text(tmp_path: Path, rows: list[list[str]], header: str = HEADER, name: str = "rec.csv") -> Path:
    """The CSV as text: header on line 1, data row r on line r + 2."""
    path = tmp_path / name
    path.write_text(header + "\n" + "".join(",".join(r) + "\n" for r in rows))
    return path


def line_of(row: int) -> int:
    return row + 2


def expect_error(path: Path, line: int | None, column: str | None, *fragments: str, **kw) -> RecordingError:
    with pytest.raises(RecordingError) as info:
        read_recording(path, **kw)
    err = info.value
    assert err.line == line
    assert err.column == column
    msg = str(err)
    if line is not None:
        assert f"line {line}" in msg
    if column is not None:
        assert f"column {column}" in msg
    for frag in fragments:
        assert frag in msg, msg
    return err


def assert_same(a: Recording, b: Recording) -> None:
    np.testing.assert_array_equal(a.seq, b.seq)
    assert a.seq.dtype == np.int64 and b.seq.dtype == np.int64
    np.testing.assert_array_equal(a.phase, b.phase)
    np.testing.assert_array_equal(a.time_s, b.time_s)
    np.testing.assert_array_equal(a.cmd, b.cmd)  # NaN == NaN for assert_array_equal
    np.testing.assert_array_equal(a.legs_mm, b.legs_mm)
    np.testing.assert_array_equal(a.meas, b.meas)
    assert list(a.extra) == list(b.extra)
    for k in a.extra:
        assert a.extra[k].dtype.kind == b.extra[k].dtype.kind
        np.testing.assert_array_equal(a.extra[k], b.extra[k])


# ---------------------------------------------------------------- round trip and reading


def test_round_trip_from_arrays_is_exact(tmp_path: Path) -> None:
    rng = np.random.default_rng(7)
    n = 12
    cmd = np.column_stack(
        [rng.uniform(-300, 300, (n, 2)), rng.uniform(2900, 3300, n), rng.uniform(-8, 8, (n, 3))]
    )
    cmd[[3, 8]] = np.nan
    meas = cmd + rng.normal(0, 0.3, (n, 6))
    meas[[3, 8]] = [1.0 / 3.0, -2.0 / 7.0, 3091.2 + 1e-13, 0.1, 0.2, 0.3]
    legs = rng.uniform(3900, 4700, (n, 6))
    phase = ["measure"] * 9 + ["verify"] * 3
    extra = {
        "temp_c": rng.uniform(15, 25, n),
        "operator": [f"op, {i}" for i in range(n)],
        "weird": [str(x) for x in rng.normal(size=n)[:-1]] + ["n/a"],
    }
    rec = recording_from_arrays(
        np.arange(100, 100 + n), phase, np.cumsum(rng.uniform(0.1, 2, n)), cmd, legs, meas, extra
    )
    path = tmp_path / "rt.csv"
    write_recording(path, rec)
    back = read_recording(path, robot=default_robot())
    assert_same(rec, back)
    assert not back.has_cmd
    assert back.extra["temp_c"].dtype == float
    assert back.extra["operator"][2] == "op, 2"
    assert back.extra["weird"].dtype.kind == "U"
    lines = path.read_text().splitlines()
    assert lines[0].split(",")[: len(REQUIRED_COLUMNS)] == list(REQUIRED_COLUMNS)
    assert lines[4].split(",")[3:9] == [""] * 6  # row index 3 (line 5) has no commanded pose


def test_round_trip_of_text_fixture(tmp_path: Path) -> None:
    rows = base_rows()
    rows = set_cell(rows, 4, "cmd_x_mm", "")
    for col in ("cmd_y_mm", "cmd_z_mm", "cmd_roll_deg", "cmd_pitch_deg", "cmd_yaw_deg"):
        rows = set_cell(rows, 4, col, "")
    first = read_recording(write_text(tmp_path, rows))
    assert first.n == 12
    assert np.all(np.isnan(first.cmd[4])) and np.all(np.isfinite(np.delete(first.cmd, 4, axis=0)))
    assert first.temp_c is not None and first.temp_c[0] == 20.5
    assert first.extra["note"][3] == "pose-3"
    assert first.meas[7, 0] == 10.07
    second_path = tmp_path / "again.csv"
    write_recording(second_path, first)
    assert_same(first, read_recording(second_path))


def test_columns_are_read_by_name_in_any_order(tmp_path: Path) -> None:
    rows = base_rows()
    order = list(reversed(range(len(COLS))))
    header = ",".join(COLS[k] for k in order)
    shuffled = [[r[k] for k in order] for r in rows]
    rec = read_recording(write_text(tmp_path, shuffled, header=header))
    straight = read_recording(write_text(tmp_path, rows, name="straight.csv"))
    assert list(rec.extra) == ["note", "temp_c"]  # extra columns keep the file's order
    assert_same(replace(rec, extra={k: rec.extra[k] for k in straight.extra}), straight)
    np.testing.assert_array_equal(rec.legs_mm[0], [4300.0, 4300.5, 4301.0, 4299.5, 4299.0, 4302.0])


def test_optional_columns_may_be_absent(tmp_path: Path) -> None:
    rows = [r[: len(REQUIRED_COLUMNS)] for r in base_rows()]
    rec = read_recording(write_text(tmp_path, rows, header=",".join(REQUIRED_COLUMNS)))
    assert rec.temp_c is None and rec.extra == {}
    assert rec.has_cmd


def test_select_keeps_order_and_columns(tmp_path: Path) -> None:
    rows = [*base_rows(10, 0), row_cells(50, "verify"), row_cells(20, "measure"), row_cells(30, "verify")]
    rec = read_recording(write_text(tmp_path, rows))
    ver = rec.select("verify")
    np.testing.assert_array_equal(ver.seq, [50, 30])
    np.testing.assert_array_equal(ver.extra["note"], ["pose-50", "pose-30"])
    np.testing.assert_array_equal(rec.select("measure").seq, [*range(10), 20])
    with pytest.raises(ValueError, match="unknown phase"):
        rec.select("calibrate")


# ---------------------------------------------------------------- file-level errors


def test_unreadable_file(tmp_path: Path) -> None:
    with pytest.raises(RecordingError, match="cannot read"):
        read_recording(tmp_path / "missing.csv")
    with pytest.raises(RecordingError, match="cannot read"):
        read_recording(tmp_path)  # a directory


def test_empty_file(tmp_path: Path) -> None:
    path = tmp_path / "empty.csv"
    path.write_text("\n\n")
    expect_error(path, 1, None, "empty")


def test_header_only_has_no_rows(tmp_path: Path) -> None:
    expect_error(write_text(tmp_path, []), None, None, "no data rows")


def test_missing_required_columns_are_all_listed(tmp_path: Path) -> None:
    drop = {COLS.index("leg4_mm"), COLS.index("meas_yaw_deg")}
    header = ",".join(c for k, c in enumerate(COLS) if k not in drop)
    rows = [[c for k, c in enumerate(r) if k not in drop] for r in base_rows()]
    expect_error(write_text(tmp_path, rows, header=header), 1, "leg4_mm, meas_yaw_deg", "missing")


def test_duplicate_column_name(tmp_path: Path) -> None:
    rows = [[*r, "1"] for r in base_rows()]
    expect_error(write_text(tmp_path, rows, header=HEADER + ",leg2_mm"), 1, "leg2_mm", "duplicate column")


def test_row_with_wrong_cell_count(tmp_path: Path) -> None:
    rows = base_rows()
    rows[5] = rows[5][:-3]
    expect_error(write_text(tmp_path, rows), line_of(5), "meas_yaw_deg", "20 cells", "23")


# ---------------------------------------------------------------- cell-level errors


@pytest.mark.parametrize("column", ["time_s", "leg3_mm", "meas_roll_deg", "cmd_z_mm", "temp_c"])
def test_cell_that_is_not_a_number(tmp_path: Path, column: str) -> None:
    rows = set_cell(base_rows(), 6, column, "12;5mm")
    expect_error(write_text(tmp_path, rows), line_of(6), column, "'12;5mm' is not a number", "(seq 6)")


def test_empty_required_cell(tmp_path: Path) -> None:
    rows = set_cell(base_rows(), 2, "leg6_mm", "")
    expect_error(write_text(tmp_path, rows), line_of(2), "leg6_mm", "empty cell")


@pytest.mark.parametrize(
    ("column", "value"),
    [
        ("leg1_mm", "nan"),
        ("meas_z_mm", "inf"),
        ("time_s", "NaN"),
        ("meas_pitch_deg", "-inf"),
        ("cmd_x_mm", "nan"),
    ],
)
def test_non_finite_required_value(tmp_path: Path, column: str, value: str) -> None:
    rows = set_cell(base_rows(), 9, column, value)
    expect_error(write_text(tmp_path, rows), line_of(9), column, "not finite")


def test_line_numbers_count_physical_lines(tmp_path: Path) -> None:
    rows = set_cell(base_rows(), 3, "leg2_mm", "abc")
    path = tmp_path / "gaps.csv"
    text = HEADER + "\n\n" + "".join(",".join(r) + "\n" for r in rows)  # blank line 2
    path.write_text(text)
    expect_error(path, 6, "leg2_mm")


def test_unknown_commanded_pose_is_allowed(tmp_path: Path) -> None:
    rows = base_rows()
    for col in COLS[3:9]:
        set_cell(rows, 1, col, "")
    rec = read_recording(write_text(tmp_path, rows))
    assert np.all(np.isnan(rec.cmd[1]))
    assert not rec.has_cmd


def test_partly_filled_cmd_group(tmp_path: Path) -> None:
    rows = base_rows()
    for col in ("cmd_x_mm", "cmd_y_mm", "cmd_roll_deg"):
        set_cell(rows, 7, col, "")
    expect_error(write_text(tmp_path, rows), line_of(7), "cmd_x_mm", "partly given", "cmd_roll_deg")


@pytest.mark.parametrize("value", ["1.5", "x7", "3e2"])
def test_seq_not_an_integer(tmp_path: Path, value: str) -> None:
    rows = set_cell(base_rows(), 4, "seq", value)
    expect_error(write_text(tmp_path, rows), line_of(4), "seq", "not an integer")


def test_duplicate_seq_names_both_lines(tmp_path: Path) -> None:
    rows = set_cell(base_rows(), 8, "seq", "3")
    err = expect_error(write_text(tmp_path, rows), line_of(8), "seq", "duplicate seq 3")
    assert f"line {line_of(3)}" in str(err)


def test_unknown_phase(tmp_path: Path) -> None:
    rows = set_cell(base_rows(), 10, "phase", "warmup")
    expect_error(write_text(tmp_path, rows), line_of(10), "phase", "'warmup'")


def test_too_few_measure_rows(tmp_path: Path) -> None:
    path = write_text(tmp_path, base_rows(n_measure=7, n_verify=5))
    expect_error(path, None, "phase", "only 7", "at least 8", "42", "residual variance")
    assert read_recording(path, min_measure_rows=7).n == 12


def test_no_verify_rows_warns_but_reads(tmp_path: Path) -> None:
    with capture_logs() as logs:
        rec = read_recording(write_text(tmp_path, base_rows(n_verify=0)))
    assert rec.n == 10
    assert any(e["log_level"] == "warning" and "verify" in e["event"] for e in logs)


# ---------------------------------------------------------------- physical range


def test_leg_length_outside_range_with_robot(tmp_path: Path) -> None:
    robot = default_robot()
    lo, hi = robot.leg_limits  # 3800..4800: the physical range is 3750..4850
    rows = set_cell(base_rows(), 5, "leg3_mm", "9999.0")
    path = write_text(tmp_path, rows)
    expect_error(path, line_of(5), "leg3_mm", "9999.0 mm", f"[{lo - 50:g}, {hi + 50:g}] mm", robot=robot)
    assert read_recording(path).legs_mm[5, 2] == 9999.0  # without a robot any positive length is accepted
    ok = set_cell(base_rows(), 5, "leg3_mm", f"{lo - 49.0}")
    assert read_recording(write_text(tmp_path, ok, name="ok.csv"), robot=robot).legs_mm[5, 2] == lo - 49.0
    below = set_cell(base_rows(), 5, "leg3_mm", f"{lo - 51.0}")
    expect_error(write_text(tmp_path, below, name="lo.csv"), line_of(5), "leg3_mm", robot=robot)


def test_leg_length_must_be_positive_without_robot(tmp_path: Path) -> None:
    rows = set_cell(base_rows(), 0, "leg1_mm", "-1.0")
    expect_error(write_text(tmp_path, rows), line_of(0), "leg1_mm", "positive")


@pytest.mark.parametrize(
    ("column", "inside", "outside"),
    [
        ("meas_x_mm", "499.0", "501.0"),  # workspace x [-300, 300] widened by 200 mm
        ("meas_z_mm", "2651.0", "2649.0"),  # z [2850, 3350]
        ("cmd_y_mm", "-499.0", "-501.0"),
        ("meas_roll_deg", "17.9", "18.1"),  # roll [-8, 8] widened by 10 deg
        ("cmd_yaw_deg", "-19.9", "-20.1"),  # yaw [-10, 10]
    ],
)
def test_pose_outside_widened_workspace(tmp_path: Path, column: str, inside: str, outside: str) -> None:
    robot = default_robot()
    good = set_cell(base_rows(), 3, column, inside)
    read_recording(write_text(tmp_path, good, name="good.csv"), robot=robot)
    bad = set_cell(base_rows(), 3, column, outside)
    expect_error(write_text(tmp_path, bad), line_of(3), column, outside, "physical range", robot=robot)


@pytest.mark.parametrize(
    ("column", "inside", "outside"),
    [
        ("meas_pitch_deg", "89.0", "90.5"),
        ("meas_roll_deg", "179.0", "180.5"),
        ("cmd_yaw_deg", "-179.0", "-181"),
    ],
)
def test_angles_without_robot(tmp_path: Path, column: str, inside: str, outside: str) -> None:
    read_recording(write_text(tmp_path, set_cell(base_rows(), 2, column, inside), name="good.csv"))
    expect_error(write_text(tmp_path, set_cell(base_rows(), 2, column, outside)), line_of(2), column)


@pytest.mark.parametrize("value", ["-0.001", "inf"])
def test_time_must_be_finite_and_non_negative(tmp_path: Path, value: str) -> None:
    rows = set_cell(base_rows(), 11, "time_s", value)
    expect_error(write_text(tmp_path, rows), line_of(11), "time_s")


@pytest.mark.parametrize("value", ["-50.5", "151"])
def test_temperature_range(tmp_path: Path, value: str) -> None:
    rows = set_cell(base_rows(), 1, "temp_c", value)
    expect_error(write_text(tmp_path, rows), line_of(1), "temp_c", "°C")
    ok = set_cell(base_rows(), 1, "temp_c", "-49.5")
    assert read_recording(write_text(tmp_path, ok, name="ok.csv")).temp_c[1] == -49.5


# ---------------------------------------------------------------- arrays constructor


def test_from_arrays_validates_like_the_reader() -> None:
    n = 9
    cmd = np.tile([0.0, 0.0, 3100.0, 0.0, 0.0, 0.0], (n, 1))
    legs = np.full((n, 6), 4300.0)
    args = (np.arange(n), ["measure"] * n, np.arange(n, dtype=float), cmd, legs, cmd.copy())
    rec = recording_from_arrays(*args)
    assert rec.n == n and rec.has_cmd and rec.seq.dtype == np.int64
    bad_legs = legs.copy()
    bad_legs[4, 1] = 5000.0
    with pytest.raises(RecordingError) as info:
        recording_from_arrays(*args[:4], bad_legs, args[5], robot=default_robot())
    assert info.value.line is None and info.value.column == "leg2_mm"
    assert "row 5 (seq 4)" in str(info.value)
    partial = cmd.copy()
    partial[2, 3] = np.nan
    with pytest.raises(RecordingError, match="partly given"):
        recording_from_arrays(*args[:3], partial, *args[4:])
    with pytest.raises(RecordingError, match="not an integer"):
        recording_from_arrays(np.arange(n) + 0.5, *args[1:])
    unknown = recording_from_arrays(*args[:3], None, *args[4:])
    assert not unknown.has_cmd


def test_values_in_errors_are_quoted_as_written_not_as_numpy_reprs() -> None:
    """A recording built from numpy arrays: the message quotes 'mesure' and 1e-300 as a user would write them."""
    rng = np.random.default_rng(3)
    n = 10
    legs = rng.uniform(3900, 4700, (n, 6))
    meas = np.tile([0.0, 0.0, 3091.2, 0.0, 0.0, 0.0], (n, 1))
    phase = np.array(["measure"] * 9 + ["mesure"])
    with pytest.raises(RecordingError) as info:
        recording_from_arrays(np.arange(n), phase, np.arange(n, dtype=float), np.full((n, 6), np.nan), legs, meas)
    assert "'mesure'" in str(info.value) and "np." not in str(info.value)
    times = np.arange(n, dtype=float)
    times[4] = -1.0
    with pytest.raises(RecordingError) as info:
        recording_from_arrays(np.arange(n), [*phase[:-1].tolist(), "verify"], times, np.full((n, 6), np.nan), legs,
                              meas)
    assert "-1.0 s is negative" in str(info.value) and "np." not in str(info.value)
