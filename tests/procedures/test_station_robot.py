"""One robot per run: the robot a station file names, the first difference between two robots in words, and the
agreement of the places that name a robot (--robot, the station file, the simulator's configuration)."""

from __future__ import annotations

from pathlib import Path

import pytest

from hilcal.robot import load_robot
from procedures.station import StationConfigError
from procedures.station_robot import agreed_robot, named_robot, robot_difference

ROOT = Path(__file__).resolve().parents[2]
SMALL = ROOT / "examples" / "hexapod_small.toml"
LEG3_A = "a_mm = [-40.15, 57.34, 0.0]"
"""Leg 3's platform joint in the small hexapod's file (the only leg with these numbers)."""


def _variant(tmp_path: Path, name: str, old: str, new: str) -> Path:
    text = SMALL.read_text()
    assert text.count(old) == 1
    path = tmp_path / name
    path.write_text(text.replace(old, new))
    return path


def test_the_same_robot_in_another_file_is_the_same_robot(tmp_path):
    copy = tmp_path / "copy.toml"
    copy.write_text("# the same machine, written again\n\n" + SMALL.read_text().replace(" = ", "="))
    assert robot_difference(load_robot(SMALL), load_robot(copy)) is None
    assert agreed_robot([("--robot", SMALL), ("the twin", copy)]) == SMALL


@pytest.mark.parametrize(("old", "new", "said"), [
    (LEG3_A, "a_mm = [-40.15, 57.84, 0.0]", "leg 3's a_mm differs: y 57.34 vs 57.84 mm"),
    ("b_mm = [61.51, -91.19, 0.0]\nl0_mm = 112.0", "b_mm = [61.51, -91.19, 0.0]\nl0_mm = 112.5",
     "leg 6's l0_mm differs: 112.0 vs 112.5 mm"),
    ("z_mm = [88.0, 115.0]", "z_mm = [88.0, 116.0]", "workspace z_mm differs: max 115.0 vs 116.0 mm"),
    ("max_mm = 152.0", "max_mm = 150.0", "leg_limits max_mm differs: 152.0 vs 150.0 mm"),
    ("[-25.0, 43.3, 10.0]", "[-25.0, 43.3, 11.0]", "cmm platform_spheres_mm 2 differs: z 10.0 vs 11.0 mm"),
])
def test_the_first_difference_is_said_with_its_place_and_both_values(tmp_path, old, new, said):
    other = _variant(tmp_path, "other.toml", old, new)
    assert robot_difference(load_robot(SMALL), load_robot(other)) == said


def test_the_names_come_first(tmp_path):
    renamed = _variant(tmp_path, "renamed.toml", 'name = "small-electric-hexapod"', 'name = "bay-2"')
    assert robot_difference(load_robot(SMALL), load_robot(renamed)) == (
        "the robot names differ: 'small-electric-hexapod' vs 'bay-2'")
    paper = load_robot(None)
    assert robot_difference(load_robot(SMALL), paper) == (
        f"the robot names differ: 'small-electric-hexapod' vs {paper.name!r}")


def test_two_robots_are_refused_naming_both_places_and_the_difference(tmp_path):
    other = _variant(tmp_path, "other.toml", LEG3_A, "a_mm = [-40.65, 57.34, 0.0]")
    with pytest.raises(StationConfigError) as refused:
        agreed_robot([(f"--robot {SMALL}", SMALL), ("the station file (the built-in robot)", None),
                      (f"the simulator's robot {other}", other)])
    message = str(refused.value)  # the first two already differ
    assert f"--robot {SMALL} and the station file (the built-in robot) are not the same robot" in message
    assert "the robot names differ" in message and "simulator" not in message
    with pytest.raises(StationConfigError) as refused:
        agreed_robot([(f"--robot {SMALL}", SMALL), (f"the simulator's robot {other}", other)])
    assert str(refused.value).startswith(f"two robots: --robot {SMALL} and the simulator's robot {other} are not the "
                                         "same robot: leg 3's a_mm differs: x -40.15 vs -40.65 mm.")


def test_nothing_named_is_the_built_in_robot_and_a_bad_file_is_refused(tmp_path):
    assert agreed_robot([]) is None and agreed_robot([("the simulator", None)]) is None
    (tmp_path / "bad.toml").write_text("name = 'x'\n")
    with pytest.raises(StationConfigError, match=r"bad\.toml"):
        agreed_robot([("--robot", tmp_path / "bad.toml"), ("the simulator", None)])


def test_a_station_file_names_its_robot_relative_to_itself(tmp_path):
    station = tmp_path / "bay" / "station.toml"
    station.parent.mkdir()
    station.write_text('robot = "robots/plant3.toml"\n[timing]\nsettle_s = 1.0\n')  # a --sim run's station: no devices
    assert named_robot(station) == station.parent.resolve() / "robots" / "plant3.toml"
    station.write_text(f'robot = "{SMALL}"\n')
    assert named_robot(station) == SMALL
    station.write_text("[timing]\nsettle_s = 1.0\n")
    assert named_robot(station) is None
    station.write_text("robot = 3\n")
    with pytest.raises(StationConfigError, match="robot file's path"):
        named_robot(station)
