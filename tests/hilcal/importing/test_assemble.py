"""`import_recording` on small hand-written files: sessions, phases, and every bad input named by file, line, column."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from hilcal.importing import HoldOut, ImportFileError, import_recording, map_from_dict
from hilcal.kinematics import Geometry, inverse_kinematics
from hilcal.recording import session_numbers
from tests.poses import feasible_random_poses

LEGS = [f"l{k}" for k in range(1, 7)]
POSE = ["x", "y", "z", "roll", "pitch", "yaw"]
MAP = {"legs": {"columns": LEGS, "unit": "mm"}, "position": {"columns": POSE[:3]},
       "orientation": {"columns": POSE[3:], "kind": "rpy_deg"}, "time": {"column": "t"}}


def _rows(robot, n: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    poses = feasible_random_poses(robot, n, np.random.default_rng(seed))
    return poses, inverse_kinematics(Geometry.nominal(robot), poses)


def _write(path: Path, robot, n: int, seed: int, t0: float = 0.0, extra: str = "") -> tuple[Path, np.ndarray]:
    poses, legs = _rows(robot, n, seed)
    lines = [",".join(["t", *LEGS, *POSE]) + extra]
    for k in range(n):
        cells = [f"{t0 + 60.0 * k:.1f}", *(repr(float(v)) for v in legs[k]), *(repr(float(v)) for v in poses[k])]
        lines.append(",".join(cells) + ("" if not extra else ",x"))
    path.write_text("\n".join(lines) + "\n")
    return path, legs


def _edit(path: Path, line: int, column: str, text: str) -> None:
    """Set one cell (1-based file line, header name)."""
    lines = path.read_text().splitlines()
    k = lines[0].split(",").index(column)
    cells = lines[line - 1].split(",")
    cells[k] = text
    lines[line - 1] = ",".join(cells)
    path.write_text("\n".join(lines) + "\n")


@pytest.fixture
def two_files(tmp_path, robot):
    a, legs_a = _write(tmp_path / "day1.csv", robot, 12, 1, t0=30.0)
    b, legs_b = _write(tmp_path / "day2.csv", robot, 6, 2, t0=500.0)
    return a, b, np.vstack([legs_a, legs_b])


def test_each_file_is_a_session_with_its_own_clock(two_files, robot):
    a, b, legs = two_files
    result = import_recording([a, b], map_from_dict(MAP), robot=robot, hold_out=HoldOut(file="day2.csv"))
    rec = result.recording
    assert list(rec.seq) == list(range(1, 19)) and np.array_equal(rec.legs_mm, legs)
    assert list(session_numbers(rec.time_s)) == [0] * 12 + [1] * 6
    assert rec.time_s[0] == 0.0 and rec.time_s[12] == 0.0 and rec.time_s[11] == 660.0
    assert list(rec.phase) == ["measure"] * 12 + ["verify"] * 6
    assert list(rec.extra["source_file"][[0, 12]]) == ["day1.csv", "day2.csv"]
    assert list(rec.extra["source_line"][[0, 11, 12]]) == [2.0, 13.0, 2.0]
    assert [(s.index, s.files, s.n_measure, s.n_verify) for s in result.sessions] == [
        (1, ("day1.csv",), 12, 0), (2, ("day2.csv",), 0, 6)]
    np.testing.assert_allclose(result.sessions[0].legs_max_mm, legs[:12].max(axis=0))


def test_without_a_time_column_the_files_are_sessions_too(two_files, robot):
    a, b, _ = two_files
    mapping = map_from_dict({k: v for k, v in MAP.items() if k != "time"})
    result = import_recording([a, b], mapping, hold_out=HoldOut(every=3))
    assert list(session_numbers(result.recording.time_s)) == [0] * 12 + [1] * 6
    assert list(result.recording.phase[:6]) == ["measure", "measure", "verify"] * 2
    assert any("no [time] column" in note for note in result.notes)


@pytest.mark.parametrize(("gap_h", "sessions"), [(1.0, 1), (5.0, 2)])
def test_a_shared_clock_decides_sessions_by_the_gap(tmp_path, robot, gap_h, sessions):
    a, _ = _write(tmp_path / "a.csv", robot, 10, 1, t0=1.7e9)
    b, _ = _write(tmp_path / "b.csv", robot, 4, 2, t0=1.7e9 + 540.0 + gap_h * 3600.0)
    mapping = map_from_dict({**MAP, "time": {"column": "t", "clock": "shared"}})
    rec = import_recording([a, b], mapping).recording
    assert session_numbers(rec.time_s).max() + 1 == sessions and rec.time_s[0] == 0.0


def test_the_phase_column_wins_over_the_hold_out(tmp_path, robot):
    path, _ = _write(tmp_path / "log.csv", robot, 10, 3, extra=",kind")
    _edit(path, 4, "kind", "check")
    mapping = map_from_dict({**MAP, "phase": {"column": "kind", "measure": "x", "verify": "check"}})
    result = import_recording([path], mapping, hold_out=HoldOut(every=2))
    assert list(np.flatnonzero(result.recording.phase == "verify")) == [2]
    assert any("--hold-out every:2 is not used" in note for note in result.notes)


def _error(paths, mapping=None, **kw) -> ImportFileError:
    with pytest.raises(ImportFileError) as info:
        import_recording(paths, map_from_dict(mapping or MAP), **kw)
    return info.value


@pytest.mark.parametrize(("line", "column", "text", "words"), [
    (5, "l3", "nan", "NaN is not a measurement"),
    (6, "y", "", "empty cell"),
    (3, "yaw", "1.2.3", "not a number"),
    (2, "l1", "4.3", "outside the robot's leg limits"),
    (7, "z", "3.1", "outside the robot's workspace"),
    (4, "t", "inf", "not finite"),
])
def test_a_bad_cell_is_named_by_file_line_and_column(tmp_path, robot, line, column, text, words):
    path, _ = _write(tmp_path / "log.csv", robot, 10, 4)
    _edit(path, line, column, text)
    err = _error([path], robot=robot)
    assert (err.source, err.line, err.column) == (str(path), line, column) and words in str(err)
    assert str(err).startswith(f"{path} line {line}, column {column}: ")


def test_missing_columns_and_files_whose_columns_disagree(two_files, robot):
    a, b, _ = two_files
    err = _error([a, b], {**MAP, "time": {"column": "stamp"}})
    assert (err.source, err.line, err.column) == (str(a), 1, "stamp") and "no such column" in str(err)
    b.write_text(b.read_text().replace("yaw", "heading", 1))
    err = _error([a, b])
    assert (err.source, err.line, err.column) == (str(b), 1, "yaw") and "columns disagree" in str(err)


def test_duplicate_rows_in_a_file_and_across_files(two_files, robot):
    a, _, _ = two_files
    lines = a.read_text().splitlines()
    a.write_text("\n".join([*lines[:6], lines[3], *lines[6:]]) + "\n")
    err = _error([a])
    assert (err.source, err.line) == (str(a), 7) and "same values as line 4" in str(err)
    a.write_text("\n".join(lines) + "\n")
    b = a.with_name("copy.csv")
    b.write_text(a.read_text())
    err = _error([a, b])
    assert (err.source, err.line) == (str(b), 2) and f"same values as {a} line 2" in str(err)
    assert "given twice" in str(_error([a, a]))


def test_skip_incomplete_leaves_out_and_lists_rows_without_a_measurement_and_repeated_rows(two_files, robot):
    """A tracker that lost its target (empty pose cells), a NaN leg reading and a sample written twice: errors in
    file order by default; with skip_incomplete the rows are left out, each named, and the rest imported as is."""
    a, b, legs = two_files
    for column in POSE:
        _edit(a, 5, column, "")  # data row 4 of day1
    _edit(b, 3, "l2", "NaN")  # data row 2 of day2
    lines = b.read_text().splitlines()
    b.write_text("\n".join([*lines, lines[-1]]) + "\n")  # day2's last row again: line 8
    err = _error([a, b])
    assert (err.source, err.line, err.column) == (str(a), 5, "x") and "empty cell" in str(err)
    result = import_recording([a, b], map_from_dict(MAP), robot=robot, hold_out=HoldOut(file="day2.csv"),
                              skip_incomplete=True)
    assert result.left_out == ("day1.csv line 5: no value in x, y, z, roll, pitch, yaw",
                               "day2.csv line 3: no value in l2",
                               "day2.csv line 8: the same values as day2.csv line 7 in every mapped column")
    kept = np.delete(np.arange(18), [3, 13])
    assert np.array_equal(result.recording.legs_mm, legs[kept])
    assert list(result.recording.extra["source_line"]) == [2, 3, 4, *range(6, 14), 2, *range(4, 8)]
    with pytest.raises(ImportFileError, match="given twice"):
        import_recording([a, a], map_from_dict(MAP), robot=robot, skip_incomplete=True)


def test_cylinder_pressures_become_leg_loads(tmp_path, robot):
    """Cap- and rod-side pressures in psi with a 180 mm bore and a 100 mm rod: force = p_cap A_cap - p_rod A_annulus
    (compression positive), worked out here with the areas in m² and 1 psi = 6894.757 Pa."""
    path, _ = _write(tmp_path / "day1.csv", robot, 10, 1)
    rng = np.random.default_rng(3)
    cap, rod = rng.uniform(500.0, 3000.0, (10, 6)), rng.uniform(100.0, 800.0, (10, 6))
    lines = path.read_text().splitlines()
    lines[0] += "," + ",".join([f"cap{k}" for k in range(1, 7)] + [f"rod{k}" for k in range(1, 7)])
    for i in range(10):
        lines[i + 1] += "," + ",".join(repr(float(v)) for v in (*cap[i], *rod[i]))
    path.write_text("\n".join(lines) + "\n")
    force = {"cap_columns": [f"cap{k}" for k in range(1, 7)], "rod_columns": [f"rod{k}" for k in range(1, 7)],
             "unit": "psi", "bore_mm": 180.0, "rod_mm": 100.0}
    rec = import_recording([path], map_from_dict({**MAP, "force": force}), robot=robot,
                           hold_out=HoldOut(every=5)).recording
    a_cap, a_annulus = np.pi / 4 * 0.180**2, np.pi / 4 * (0.180**2 - 0.100**2)
    expected_kn = (cap * a_cap - rod * a_annulus) * 6894.757 / 1000.0
    got = np.column_stack([rec.extra[f"leg{k}_force_kn"] for k in range(1, 7)])
    np.testing.assert_allclose(got, expected_kn, rtol=1e-6)
    with pytest.raises(ValueError, match="need cap_columns and bore_mm"):
        map_from_dict({**MAP, "force": {"cap_columns": force["cap_columns"], "unit": "bar"}})


def test_a_unit_that_does_not_fit_is_named(tmp_path, robot):
    path, _ = _write(tmp_path / "log.csv", robot, 10, 5)
    err = _error([path], {**MAP, "orientation": {"columns": POSE[3:], "kind": "rpy_rad"}}, robot=robot)
    assert err.line is not None and err.column in POSE[3:] and "are these degrees" in str(err)
    err = _error([path], {**MAP, "legs": {"columns": LEGS, "unit": "m"}}, robot=robot)
    assert (err.line, err.column) == (2, "l1")


def test_rows_that_do_not_match_the_header_and_unknown_phases(tmp_path, robot):
    path, _ = _write(tmp_path / "log.csv", robot, 10, 6)
    lines = path.read_text().splitlines()
    path.write_text("\n".join([*lines[:4], lines[4].rsplit(",", 2)[0], *lines[5:]]) + "\n")
    err = _error([path])
    assert (err.line, err.column) == (5, "pitch") and "cells" in str(err)
    path, _ = _write(tmp_path / "phase.csv", robot, 10, 6, extra=",kind")
    _edit(path, 9, "kind", "verfy")
    err = _error([path], {**MAP, "phase": {"column": "kind", "measure": "x"}})
    assert (err.line, err.column) == (9, "kind") and "'verfy'" in str(err)


def test_hold_out_file_must_exist_and_too_few_measure_rows_are_named(two_files, robot):
    a, b, _ = two_files
    err = _error([a, b], hold_out=HoldOut(file="day3.csv"))
    assert err.source == "--hold-out" and "day1.csv, day2.csv" in str(err)
    err = _error([a], hold_out=HoldOut(every=2))
    assert err.column == "phase" and "only 6 'measure' row(s)" in str(err)


def test_a_file_whose_clock_cannot_restart_is_refused(tmp_path, robot):
    """After a one-row file, a clock from 0 does not go back: the two files would be one session."""
    a, _ = _write(tmp_path / "a.csv", robot, 1, 7)
    b, _ = _write(tmp_path / "b.csv", robot, 10, 8)
    err = _error([a, b])
    assert (err.source, err.line, err.column) == (str(b), 2, "t") and "does not restart" in str(err)
    assert len(import_recording([b, a], map_from_dict(MAP)).sessions) == 2
