"""Robot files: the built-in paper robot and a clear error for each kind of bad file."""

from __future__ import annotations

import tomllib
from importlib import resources
from pathlib import Path

import numpy as np
import pytest

from hilcal.robot import RobotFileError, load_robot, robot_from_dict


def _default_data() -> dict:
    return tomllib.loads(resources.files("hilcal.data").joinpath("paper_table1.toml").read_text())


def test_default_robot_is_paper_table1(robot):
    # Table 1 of the paper, leg 3 and leg 6, typed from the paper.
    assert robot.a[2].tolist() == [-803.0, 1146.8, 0.0]
    assert robot.b[5].tolist() == [2049.3, -3038.5, 0.0]
    # Table 1's l_i columns are a_i + t_home - b_i; leg 2: (-2198.5, -2025.2, 3091.2)
    l2 = robot.a[1] + robot.home[:3] - robot.b[1]
    np.testing.assert_allclose(l2, [-2198.5, -2025.2, 3091.2], atol=1e-9)
    assert robot.moving_mass_kg == 4000.0
    assert robot.com.tolist() == [0.0, 0.0, 300.0]
    assert robot.workspace[2].tolist() == [2850.0, 3350.0]
    assert robot.workspace[5].tolist() == [-10.0, 10.0]


def _expect_error(data: dict, *fragments: str) -> None:
    with pytest.raises(RobotFileError) as info:
        robot_from_dict(data, "test.toml")
    for fragment in fragments:
        assert fragment in str(info.value)


def test_five_legs_rejected():
    data = _default_data()
    data["legs"] = data["legs"][:5]
    _expect_error(data, "legs", "at least 6")


def test_short_vector_names_the_leg():
    data = _default_data()
    data["legs"][2]["a_mm"] = [1.0, 2.0]
    _expect_error(data, "legs.3.a_mm")


def test_typo_field_rejected():
    data = _default_data()
    data["mass"]["moving_mas_kg"] = 1.0
    _expect_error(data, "mass.moving_mas_kg")


def test_workspace_order():
    data = _default_data()
    data["workspace"]["z_mm"] = [3350.0, 2850.0]
    _expect_error(data, "workspace.z_mm", "below")


def test_home_outside_workspace():
    data = _default_data()
    data["home"]["x_mm"] = 500.0
    _expect_error(data, "home.x_mm")


def test_home_violates_leg_limits():
    data = _default_data()
    data["leg_limits"] = {"min_mm": 4400.0, "max_mm": 4800.0}
    _expect_error(data, "leg 1 length at home")


def test_collinear_spheres():
    data = _default_data()
    data["cmm"]["platform_spheres_mm"] = [[0.0, 0.0, 0.0], [100.0, 0.0, 0.0], [200.0, 0.0, 0.0]]
    _expect_error(data, "collinear")


def test_coincident_joints():
    data = _default_data()
    data["legs"][1]["b_mm"] = data["legs"][0]["b_mm"]
    _expect_error(data, "coincident b_mm")


def test_negative_mass_and_nan():
    data = _default_data()
    data["mass"]["moving_mass_kg"] = -1.0
    _expect_error(data, "mass.moving_mass_kg")
    data = _default_data()
    data["home"]["z_mm"] = float("nan")
    _expect_error(data, "home.z_mm")


def test_unreadable_and_not_toml(tmp_path: Path):
    with pytest.raises(RobotFileError, match="cannot read"):
        load_robot(tmp_path / "missing.toml")
    bad = tmp_path / "bad.toml"
    bad.write_text("legs = [\n")
    with pytest.raises(RobotFileError, match="not valid TOML"):
        load_robot(bad)
