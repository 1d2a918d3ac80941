"""Leg wiring: readings in another order than the robot file's legs, or counting the wrong way, are found, named and
undone; healthy recordings pass untouched."""

from __future__ import annotations

import dataclasses
import shutil

import numpy as np
import pytest

from hilcal.discovery.search import WIRING, diagnose
from hilcal.importing import import_recording, load_map, parse_hold_out
from hilcal.recording import read_recording
from hilcal.robot import load_robot
from hilcal.wiring import check_wiring
from tests.hilcal.importing.support import EXAMPLES as IMPORT_EXAMPLES

EXAMPLES = IMPORT_EXAMPLES.parent


def _example(name: str):
    robot = load_robot(EXAMPLES / name / "robot.toml")
    return robot, read_recording(EXAMPLES / name / "recording.csv", robot)


@pytest.mark.parametrize("name", ["electric_hexapod", "small_hexapod"])
def test_healthy_recordings_pass(name):
    robot, rec = _example(name)
    wiring = check_wiring(rec.legs_mm, rec.meas, robot)
    assert wiring.checked and not wiring.problem
    assert np.all(wiring.misfit_mm < 0.05) and np.all(wiring.slope > 0.9)


def test_swapped_and_reversed_legs_are_found_and_undone():
    robot, rec = _example("small_hexapod")
    wired = rec.legs_mm[:, [0, 2, 1, 3, 4, 5]].copy()
    wired[:, 4] = 500.0 - wired[:, 4]
    wiring = check_wiring(wired, rec.meas, robot)
    assert wiring.reordered and wiring.reversed_legs == (5,) and not wiring.dead
    assert list(wiring.column_of_leg) == [0, 2, 1, 3, 4, 5]
    fixed = wiring.corrected(wired)
    np.testing.assert_array_equal(np.delete(fixed, 4, axis=1), np.delete(rec.legs_mm, 4, axis=1))
    offset = fixed[:, 4] - rec.legs_mm[:, 4]
    assert np.ptp(offset) < 1e-9 and abs(offset[0]) < 0.1, "mirrored about the fitted offset (a dl0 is left)"
    text = wiring.sentence([f"L{i}" for i in range(1, 7)])
    assert "leg 2 is 'L3'" in text and "leg 3 is 'L2'" in text and "leg(s) 5 read(s) less" in text


def test_another_numbering_of_the_same_machine_is_found():
    robot, rec = _example("electric_hexapod")
    wiring = check_wiring(rec.legs_mm[:, [1, 2, 3, 4, 5, 0]], rec.meas, robot)
    assert list(wiring.column_of_leg) == [5, 0, 1, 2, 3, 4] and not wiring.reversed_legs


def test_a_dead_transducer_follows_no_leg():
    robot, rec = _example("small_hexapod")
    wired = rec.legs_mm.copy()
    wired[:, 3] = 250.0 + np.random.default_rng(0).normal(0.0, 0.01, rec.n)
    wiring = check_wiring(wired, rec.meas, robot)
    assert wiring.dead == (3,) and "follow(s) no leg" in wiring.sentence()


@pytest.mark.slow
def test_diagnose_names_the_wiring_first_and_still_finds_the_scale_fault():
    robot, rec = _example("electric_hexapod")
    wired = rec.legs_mm[:, [0, 2, 1, 3, 4, 5]].copy()
    wired[:, 4] = 500.0 - wired[:, 4]
    diag = diagnose(dataclasses.replace(rec, legs_mm=wired), robot)
    assert diag.effect == WIRING and diag.effects[1] == "sensor_scale"
    assert diag.summary[0].startswith("Set-up fault (leg wiring)") and "'leg3_mm'" in diag.summary[0]
    assert diag.parameters["leg2_sensor_scale_ppm"] == pytest.approx(62500.0, rel=0.01)
    assert diag.to_json()["wiring"]["column_of_leg"] == [1, 3, 2, 4, 5, 6]


def test_import_suggests_the_column_order(tmp_path):
    folder = tmp_path / "logger"
    shutil.copytree(IMPORT_EXAMPLES / "logger", folder)
    text = (folder / "map.toml").read_text()
    (folder / "map.toml").write_text(text.replace('"leg_length_1", "leg_length_2"', '"leg_length_2", "leg_length_1"',
                                                  1))
    robot = load_robot(folder / "robot.toml")
    result = import_recording([folder / "day1.csv", folder / "day2.csv"], load_map(folder / "map.toml"), robot=robot,
                              hold_out=parse_hold_out("file:day2.csv"))
    note = next(n for n in result.notes if n.startswith("leg wiring"))
    assert 'set [legs] columns = ["leg_length_1", "leg_length_2", "leg_length_3"' in note


def test_import_says_how_to_read_a_reversed_leg_and_the_fix_reads_it(tmp_path):
    """Leg 4 mapped with the wrong sign: the note gives mm_per_unit and zero_mm that read it the right way, and an
    import with them gives leg 4 as the correct map does (slope exact; the zero within a tenth of a mm, since it is
    fitted to the nominal geometry)."""
    folder = tmp_path / "logger"
    shutil.copytree(IMPORT_EXAMPLES / "logger", folder)
    robot = load_robot(folder / "robot.toml")
    files = [folder / "day1.csv", folder / "day2.csv"]
    right = import_recording(files, load_map(folder / "map.toml"), robot=robot).recording.legs_mm
    text = (folder / "map.toml").read_text()
    wrong = text.replace("mm_per_unit = [5.0, 5.0, 5.0, 5.0, 5.0, 5.0]",
                         "mm_per_unit = [5.0, 5.0, 5.0, -5.0, 5.0, 5.0]")
    wrong = wrong.replace("zero_mm = [812.0, 812.0, 812.0, 812.0, 812.0, 812.0]",
                          "zero_mm = [812.0, 812.0, 812.0, 969.0, 812.0, 812.0]")  # within the leg limits
    assert wrong.count("-5.0") == 1 and "969.0" in wrong
    (folder / "map.toml").write_text(wrong)
    note = next(n for n in import_recording(files, load_map(folder / "map.toml"), robot=robot).notes
                if n.startswith("leg wiring"))
    assert "leg(s) 4 read(s) less" in note
    suggested = note.split("to read them the right way set [legs] ", 1)[1].split(" (the new zeros", 1)[0]
    scale, zero = suggested.split(" and ")
    assert scale == "mm_per_unit = [5, 5, 5, 5, 5, 5]"
    (folder / "map.toml").write_text(
        wrong.replace("mm_per_unit = [5.0, 5.0, 5.0, -5.0, 5.0, 5.0]", scale).replace(
            "zero_mm = [812.0, 812.0, 812.0, 969.0, 812.0, 812.0]", zero))
    fixed = import_recording(files, load_map(folder / "map.toml"), robot=robot).recording.legs_mm
    offset = fixed[:, 3] - right[:, 3]
    assert np.ptp(offset) < 1e-6 and abs(offset[0]) < 0.1
    np.testing.assert_allclose(np.delete(fixed, 3, axis=1), np.delete(right, 3, axis=1), atol=1e-9)
