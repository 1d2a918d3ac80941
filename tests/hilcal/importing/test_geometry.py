"""Robot files from documented geometry: the paper's Table 1 from its radii and pair spacings, and the checks."""

from __future__ import annotations

import numpy as np
import pytest

from hilcal.importing import GeometrySpec, ImportFileError, check_geometry, geometry_robot_toml, load_geometry
from hilcal.robot import load_robot

PAPER = {
    "name": "paper-from-geometry",
    "base": {"radius_mm": 3665.0, "pair_spacing_deg": 8.0},
    "platform": {"radius_mm": 1400.0, "pair_spacing_deg": 10.0},
    "legs": {"min_mm": 3800.0, "stroke_mm": 1000.0},
    "home": {"z_mm": 3091.2},
    "travel": {"x_mm": 300.0, "y_mm": 300.0, "z_mm": [-241.2, 258.8], "roll_deg": 8.0, "pitch_deg": 8.0,
               "yaw_deg": 10.0},
    "mass": {"moving_mass_kg": 4000.0, "com_mm": [0.0, 0.0, 300.0]},
}


def test_the_paper_robot_from_its_joint_circles(robot, tmp_path):
    """The paper's Table 1 joints (hilcal/data/paper_table1.toml) lie on circles of 3665 and 1400 mm in pairs 8 and
    10 degrees apart; its values are rounded to 0.1 mm, so the rebuilt joints agree to a few tenths of a mm."""
    made, text, _ = geometry_robot_toml(GeometrySpec.model_validate(PAPER), "paper.toml")
    assert np.abs(made.a - robot.a).max() < 0.2 and np.abs(made.b - robot.b).max() < 0.2
    path = tmp_path / "robot.toml"
    path.write_text(text)
    again = load_robot(path)
    np.testing.assert_array_equal(again.workspace, robot.workspace)
    assert again.leg_limits == robot.leg_limits and np.array_equal(again.l0, robot.l0)
    assert "nominal layout" in text and again.platform_spheres.shape == (3, 3)


def test_home_from_the_leg_length_and_explicit_angles():
    spec = {**PAPER, "home": {"leg_mm": 4300.0},
            "platform": {"radius_mm": 1400.0, "angles_deg": [5.0, 115.0, 125.0, 235.0, 245.0, 355.0]}}
    made, _, _ = geometry_robot_toml(GeometrySpec.model_validate(spec), "g.toml")
    check = check_geometry(made)
    np.testing.assert_allclose(check.home_legs_mm, 4300.0, atol=1e-9)
    assert 0 < check.corners_reachable <= 64 and 0.5 < check.reachable_fraction <= 1.0


@pytest.mark.parametrize(("change", "words"), [
    ({"home": {"z_mm": 1000.0}}, "outside leg_limits"),
    ({"home": {"leg_mm": 100.0}}, "shorter than the horizontal joint distance"),
    ({"base": {"radius_mm": 3665.0}}, "either angles_deg"),
    ({"home": {"z_mm": 3091.2, "leg_mm": 4300.0}}, "either z_mm"),
    ({"travel": {**PAPER["travel"], "pitch_deg": 95.0}}, "inside (-90, 90)"),
])
def test_numbers_that_make_no_robot_are_named(tmp_path, change, words):
    path = tmp_path / "g.toml"
    lines = []
    for section, table in {**PAPER, **change}.items():
        if isinstance(table, dict):
            lines.append(f"[{section}]")
            lines += [f"{k} = {v!r}" for k, v in table.items()]
        else:
            lines.insert(0, f"{section} = {table!r}".replace("'", '"'))
    path.write_text("\n".join(lines) + "\n")
    with pytest.raises(ImportFileError) as info:
        geometry_robot_toml(load_geometry(path), str(path))
    assert words in str(info.value) and str(info.value).startswith(str(path))


def test_travel_and_mass_left_out_get_stated_defaults():
    """A newcomer may not know the travel or the moving mass: the robot file still comes, with the defaults said."""
    spec = {k: v for k, v in PAPER.items() if k not in ("travel", "mass")}
    made, text, defaults = geometry_robot_toml(GeometrySpec.model_validate(spec), "g.toml")
    assert [note.split(":")[0] for note in defaults.notes] == ["mass", "travel"]
    plate_kg = 2700.0 * np.pi * (1.2 * 1.4) ** 2 * 0.020  # aluminium, 1.2 x the 1400 mm joint radius, 20 mm thick
    assert made.moving_mass_kg == pytest.approx(plate_kg, abs=0.01)
    check = check_geometry(made)
    assert check.corners_reachable == 64, "the default travel box is one whose corners the legs reach"
    half = (made.workspace[:, 1] - made.workspace[:, 0]) / 2
    np.testing.assert_allclose(made.workspace.mean(axis=1), made.home, atol=1e-9)
    assert np.all(half > 0)
    assert "# Default travel: not in the geometry file" in text and "# Default mass:" in text
