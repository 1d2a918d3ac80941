"""`hilcal import` and `hilcal robot-from-geometry` on the command line: the worked examples, the summary, and exit
code 2 with file, line and column on bad input, with no output file written (and an existing one left alone)."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from hilcal.recording import read_recording, session_numbers
from hilcal.robot import load_robot
from procedures.cli.app import app

runner = CliRunner()


def _flat(text: str) -> str:
    """Output without any whitespace: rich wraps long paths anywhere, even inside a word."""
    return "".join(text.split())
EXAMPLES = Path(__file__).resolve().parents[2] / "examples" / "import"
LOGGER = EXAMPLES / "logger"


def _logger_args(folder: Path, out: Path) -> list[str]:
    return ["import", str(folder / "day1.csv"), str(folder / "day2.csv"), "--map", str(folder / "map.toml"),
            "--robot", str(LOGGER / "robot.toml"), "--hold-out", "file:day2.csv", "--out", str(out)]


@pytest.fixture
def logger_copy(tmp_path) -> Path:
    folder = tmp_path / "logger"
    shutil.copytree(LOGGER, folder)
    return folder


def test_the_logger_example_imports_with_a_summary_per_session(tmp_path):
    out = tmp_path / "rec.csv"
    result = runner.invoke(app, _logger_args(LOGGER, out))
    assert result.exit_code == 0, result.output
    assert "day1.csv" in result.stdout and "day2.csv" in result.stdout and "leg6_mm" in result.stdout
    assert _flat("66 rows (45 measure, 21 verify) in 2 session(s)") in _flat(result.stdout)
    rec = read_recording(out, load_robot(LOGGER / "robot.toml"))
    assert list(np.unique(session_numbers(rec.time_s), return_counts=True)[1]) == [45, 21]
    assert set(rec.phase[45:]) == {"verify"} and not rec.has_cmd


def test_json_summary(tmp_path):
    folder = EXAMPLES / "tracker"
    result = runner.invoke(app, ["import", str(folder / "tracker_export.csv"), "--map", str(folder / "map.toml"),
                                 "--hold-out", "every:3", "--out", str(tmp_path / "t.csv"), "--json"])
    assert result.exit_code == 0, result.output
    data = json.loads(result.stdout)
    assert (data["rows"], data["measure"], data["verify"]) == (48, 32, 16)
    assert len(data["sessions"]) == 1 and data["sessions"][0]["at_extreme"] is None
    assert len(data["sessions"][0]["legs_min_mm"]) == 6
    assert "sphere_fit_rms_mm" in read_recording(tmp_path / "t.csv").extra


def test_robot_from_geometry_writes_the_committed_robot_file(tmp_path):
    out = tmp_path / "robot.toml"
    result = runner.invoke(app, ["robot-from-geometry", str(LOGGER / "geometry.toml"), "--out", str(out)])
    assert result.exit_code == 0, result.output
    assert "887.000" in result.stdout and "of 64 corners" in result.stdout
    assert out.read_text() == (LOGGER / "robot.toml").read_text()
    robot = load_robot(out)
    assert robot.leg_limits == (812.0, 962.0) and robot.actuator_kind == "electric"


def _replace_cell(path: Path, line: int, column: str, text: str, delimiter: str = ",") -> None:
    lines = path.read_text().splitlines()
    k = lines[0].split(delimiter).index(column)
    cells = lines[line - 1].split(delimiter)
    cells[k] = text
    lines[line - 1] = delimiter.join(cells)
    path.write_text("\n".join(lines) + "\n")


def _quaternion_norm_5(folder: Path) -> None:
    lines = (folder / "day1.csv").read_text().splitlines()
    header = lines[0].split(",")
    cells = lines[3].split(",")
    for name in ("orientation_x", "orientation_y", "orientation_z", "orientation_w"):
        k = header.index(name)
        cells[k] = repr(5 * float(cells[k]))
    lines[3] = ",".join(cells)
    (folder / "day1.csv").write_text("\n".join(lines) + "\n")


def _duplicate_line(folder: Path) -> None:
    lines = (folder / "day2.csv").read_text().splitlines()
    (folder / "day2.csv").write_text("\n".join([*lines[:5], lines[2], *lines[5:]]) + "\n")


BAD = {
    "a column that does not exist": (
        lambda f: (f / "map.toml").write_text((f / "map.toml").read_text().replace('"stamp"', '"time"')),
        "day1.csv", 1, "time", "no such column"),
    "legs of 3 mm (zero_mm forgotten)": (
        lambda f: (f / "map.toml").write_text((f / "map.toml").read_text().replace("812.0", "0.0")),
        "day1.csv", 2, "leg_length_1", "outside the robot's leg limits"),
    "quaternions of norm 5": (_quaternion_norm_5, "day1.csv", 4, "orientation_x", "norm 5"),
    "a NaN": (lambda f: _replace_cell(f / "day1.csv", 7, "position_y", "NaN"), "day1.csv", 7, "position_y", "NaN"),
    "a duplicate row": (_duplicate_line, "day2.csv", 6, "leg_length_1", "same values as line 3"),
    "files whose columns disagree": (
        lambda f: (f / "day2.csv").write_text((f / "day2.csv").read_text().replace("status,", "state,", 1)),
        "day2.csv", 1, "status", "columns disagree"),
    "positions in m read as mm": (
        lambda f: (f / "map.toml").write_text((f / "map.toml").read_text().replace('unit = "mm"', 'unit = "m"')),
        "day1.csv", 2, "position_x", "outside the robot's workspace"),
}


@pytest.mark.parametrize("case", list(BAD))
def test_bad_input_exits_2_names_file_line_column_and_writes_nothing(logger_copy, tmp_path, case):
    spoil, file_name, line, column, words = BAD[case]
    spoil(logger_copy)
    out = tmp_path / "rec.csv"
    result = runner.invoke(app, _logger_args(logger_copy, out))
    assert result.exit_code == 2, result.output
    message = _flat(result.output)
    assert _flat(f"{logger_copy / file_name} line {line}, column {column}:") in message and _flat(words) in message
    assert not out.exists() and not list(tmp_path.glob(".rec.csv*"))


def test_a_row_without_a_measurement_is_an_error_that_points_at_skip_incomplete(logger_copy, tmp_path):
    day1 = logger_copy / "day1.csv"
    lines = day1.read_text().splitlines()
    header = lines[0].split(",")
    at = 3  # the third data row (file line 4)
    cells = lines[at].split(",")
    cells[len(header) - 1] = ""
    lines[at] = ",".join(cells)
    day1.write_text("\n".join(lines) + "\n")
    out = tmp_path / "rec.csv"
    failed = runner.invoke(app, _logger_args(logger_copy, out))
    assert failed.exit_code == 2 and "--skip-incomplete" in _flat(failed.output) and not out.exists()
    done = runner.invoke(app, [*_logger_args(logger_copy, out), "--skip-incomplete", "--json"])
    assert done.exit_code == 0, done.output
    summary = json.loads(done.stdout)
    assert summary["left_out"] == [f"day1.csv line {at + 1}: no value in {header[-1]}"] and summary["rows"] == 65


def test_legs_in_m_read_as_mm_are_legs_of_4_mm(tmp_path):
    folder = tmp_path / "tracker"
    shutil.copytree(EXAMPLES / "tracker", folder)
    (folder / "map.toml").write_text((folder / "map.toml").read_text().replace('unit = "m"', 'unit = "mm"', 1))
    out = tmp_path / "t.csv"
    paper_robot = EXAMPLES.parents[1] / "hilcal" / "data" / "paper_table1.toml"
    result = runner.invoke(app, ["import", str(folder / "tracker_export.csv"), "--map", str(folder / "map.toml"),
                                 "--robot", str(paper_robot), "--out", str(out)])
    message = _flat(result.output)
    assert result.exit_code == 2 and _flat(f"{folder / 'tracker_export.csv'} line 5, column Leg 1 [m]:") in message
    assert _flat("= 4.54617 mm, outside the robot's leg limits") in message and not out.exists()


def test_an_existing_output_is_left_alone_on_bad_input(logger_copy, tmp_path):
    out = tmp_path / "rec.csv"
    out.write_text("keep me\n")
    _replace_cell(logger_copy / "day2.csv", 3, "leg_length_4", "abc")
    result = runner.invoke(app, _logger_args(logger_copy, out))
    assert result.exit_code == 2 and _flat("line 3, column leg_length_4") in _flat(result.output)
    assert out.read_text() == "keep me\n"


@pytest.mark.parametrize(("args", "words"), [
    (["--hold-out", "every:1"], "every:N needs N >= 2"),
    (["--hold-out", "file:day3.csv"], "names none of the input files"),
    (["--map", "missing.toml"], "cannot read the mapping file"),
])
def test_bad_options_exit_2(tmp_path, args, words):
    out = tmp_path / "rec.csv"
    base = _logger_args(LOGGER, out)
    for option, value in zip(args[::2], args[1::2], strict=True):
        base[base.index(option) + 1] = value
    result = runner.invoke(app, base)
    assert result.exit_code == 2 and _flat(words) in _flat(result.output) and not out.exists()


def test_the_output_may_not_be_an_input(logger_copy):
    day1 = logger_copy / "day1.csv"
    before = day1.read_text()
    result = runner.invoke(app, _logger_args(logger_copy, day1))
    assert result.exit_code == 2 and _flat("is one of the input files") in _flat(result.output)
    assert day1.read_text() == before


def test_a_geometry_that_is_not_a_robot_exits_2(tmp_path):
    bad = tmp_path / "geometry.toml"
    bad.write_text((LOGGER / "geometry.toml").read_text().replace("leg_mm = 887.0", "leg_mm = 700.0"))
    result = runner.invoke(app, ["robot-from-geometry", str(bad), "--out", str(tmp_path / "r.toml")])
    assert result.exit_code == 2 and "leg_limits" in result.output and not (tmp_path / "r.toml").exists()
    bad.write_text((LOGGER / "geometry.toml").read_text().replace("pair_spacing_deg = 16.0", ""))
    result = runner.invoke(app, ["robot-from-geometry", str(bad), "--out", str(tmp_path / "r.toml")])
    assert result.exit_code == 2 and _flat("key base") in _flat(result.output)
