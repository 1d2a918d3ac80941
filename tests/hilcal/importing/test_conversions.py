"""Units and orientations into mm and degrees, against scipy's Rotation (an independent implementation)."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from hilcal.importing import map_from_dict
from hilcal.importing.conversions import check_legs, check_pose, legs_mm, orientation_deg, position_mm
from hilcal.importing.errors import ValueProblem
from hilcal.importing.mapping import OrientationMap


def _rpy(n: int, rng: np.random.Generator) -> np.ndarray:
    """Roll, pitch, yaw (deg) over the whole sphere of rotations except gimbal lock."""
    return np.column_stack([rng.uniform(-179, 179, n), rng.uniform(-89, 89, n), rng.uniform(-179, 179, n)])


def _scipy(rpy_deg: np.ndarray) -> Rotation:
    return Rotation.from_euler("ZYX", rpy_deg[:, ::-1], degrees=True)


def test_quaternions_both_orders_and_either_sign(rng):
    rpy = _rpy(200, rng)
    xyzw = _scipy(rpy).as_quat()
    np.testing.assert_allclose(orientation_deg(xyzw, "quaternion_xyzw"), rpy, atol=1e-9)
    np.testing.assert_allclose(orientation_deg(-xyzw[:, [3, 0, 1, 2]], "quaternion_wxyz"), rpy, atol=1e-9)


def test_rotation_matrix_row_major_and_rpy_in_radians(rng):
    rpy = _rpy(200, rng)
    np.testing.assert_allclose(orientation_deg(_scipy(rpy).as_matrix().reshape(-1, 9), "matrix"), rpy, atol=1e-9)
    np.testing.assert_allclose(orientation_deg(np.radians(rpy), "rpy_rad"), rpy, atol=1e-9)
    assert np.array_equal(orientation_deg(rpy, "rpy_deg"), rpy)


def test_a_quaternion_written_with_few_digits_is_normalised(rng):
    rpy = _rpy(20, rng)
    rounded = np.round(_scipy(rpy).as_quat(), 6)
    np.testing.assert_allclose(orientation_deg(rounded, "quaternion_xyzw"), rpy, atol=2e-4)


@pytest.mark.parametrize(("values", "kind", "row", "words"), [
    (np.array([[0.0, 0.0, 0.0, 1.0], [0.0, 0.0, 0.0, 5.0]]), "quaternion_xyzw", 1, "norm 5"),
    (np.array([[0.1, 0.2, 0.3], [10.0, 5.0, 3.0]]), "rpy_rad", 1, "are these degrees"),
    (np.array([np.eye(3).ravel(), 2 * np.eye(3).ravel()]), "matrix", 1, "not orthonormal"),
    (np.array([np.diag([1.0, 1.0, -1.0]).ravel()]), "matrix", 0, "reflection"),
])
def test_values_that_do_not_fit_the_kind_name_their_row(values, kind, row, words):
    with pytest.raises(ValueProblem) as info:
        orientation_deg(values, kind)
    assert info.value.row == row and words in str(info.value)


def test_leg_units_give_the_documented_lengths():
    rev = map_from_dict({"legs": {"columns": list("abcdef"), "unit": "rev", "mm_per_unit": 5.0, "zero_mm": 812.0},
                         "position": {"columns": list("xyz")}, "orientation": {"columns": list("rpw"),
                                                                                "kind": "rpy_deg"}}).legs
    assert np.array_equal(legs_mm(np.full((1, 6), 10.0), rev), np.full((1, 6), 862.0))
    metres = rev.model_copy(update={"unit": "m", "mm_per_unit": None, "zero_mm": None})
    assert np.array_equal(legs_mm(np.full((1, 6), 4.3), metres), np.full((1, 6), 4300.0))
    assert np.array_equal(position_mm(np.array([[0.25, -0.5, 3.0]]), "m"), np.array([[250.0, -500.0, 3000.0]]))


def test_legs_of_3_mm_do_not_fit_the_robot(robot):
    legs = map_from_dict({"legs": {"columns": list("abcdef"), "unit": "mm"}, "position": {"columns": list("xyz")},
                          "orientation": {"columns": list("rpw"), "kind": "rpy_deg"}}).legs
    readings = np.full((3, 6), 4300.0)
    readings[2, 4] = 3.0
    check_legs(readings[:2], readings[:2], legs, robot)
    with pytest.raises(ValueProblem) as info:
        check_legs(readings, readings, legs, robot)
    assert (info.value.row, info.value.column) == (2, 4) and "[3750, 4850] mm" in str(info.value)
    with pytest.raises(ValueProblem):
        check_legs(-readings, -readings, legs, None)


def test_a_pose_in_metres_read_as_mm_is_outside_the_workspace(robot):
    pose = np.array([[0.1, 0.2, 3.09, 1.0, 2.0, 3.0]])
    check_pose(pose, None)
    with pytest.raises(ValueProblem) as info:
        check_pose(pose, robot)
    assert info.value.column == 2 and "z_mm = 3.09" in str(info.value)


def test_without_a_robot_a_forgotten_zero_is_caught_by_the_legs_range():
    legs = map_from_dict({"legs": {"columns": list("abcdef"), "unit": "rev", "mm_per_unit": 5.0, "zero_mm": 0.0},
                          "position": {"columns": list("xyz")},
                          "orientation": {"columns": list("rpw"), "kind": "rpy_deg"}}).legs
    readings = np.tile(np.linspace(5.0, 25.0, 5)[:, None], (1, 6))
    readings[3, 2] = 0.6
    check_legs(legs_mm(readings, legs)[:3], readings[:3], legs, None)
    with pytest.raises(ValueProblem) as info:
        check_legs(legs_mm(readings, legs), readings, legs, None)
    assert (info.value.row, info.value.column) == (3, 2) and "more than 3 times" in str(info.value)


def _rx(a: float) -> np.ndarray:
    c, s = np.cos(np.radians(a)), np.sin(np.radians(a))
    return np.array([[1, 0, 0], [0, c, -s], [0, s, c]])


def _ry(a: float) -> np.ndarray:
    c, s = np.cos(np.radians(a)), np.sin(np.radians(a))
    return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])


def _rz(a: float) -> np.ndarray:
    c, s = np.cos(np.radians(a)), np.sin(np.radians(a))
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])


def test_euler_sequences_about_moving_and_fixed_axes_match_hand_built_matrices():
    a, b, c = 12.0, -7.5, 31.0
    moving = _rx(a) @ _ry(b) @ _rz(c)
    fixed = _rz(c) @ _ry(b) @ _rx(a)
    expected_moving = orientation_deg(moving.reshape(1, 9), "matrix")
    expected_fixed = orientation_deg(fixed.reshape(1, 9), "matrix")
    np.testing.assert_allclose(orientation_deg(np.array([[a, b, c]]), "euler_deg", "XYZ"), expected_moving, atol=1e-9)
    np.testing.assert_allclose(orientation_deg(np.array([[a, b, c]]), "euler_deg", "xyz"), expected_fixed, atol=1e-9)
    np.testing.assert_allclose(orientation_deg(np.radians([[c, b, a]]), "euler_rad", "ZYX"), [[a, b, c]], atol=1e-9)


def test_rotation_vectors_in_degrees_and_radians():
    np.testing.assert_allclose(orientation_deg(np.array([[0.0, 0.0, 30.0]]), "rotvec_deg"), [[0, 0, 30]], atol=1e-9)
    np.testing.assert_allclose(orientation_deg(np.array([[np.radians(-20.0), 0, 0]]), "rotvec_rad"), [[-20, 0, 0]],
                               atol=1e-9)
    with pytest.raises(ValueProblem, match="are these degrees"):
        orientation_deg(np.array([[0.0, 0.0, 0.1], [0.0, 0.0, 30.0]]), "rotvec_rad")


@pytest.mark.parametrize(("orientation", "words"), [
    ({"columns": ["a", "b", "c"], "kind": "euler_deg"}, "needs sequence"),
    ({"columns": ["a", "b", "c"], "kind": "euler_deg", "sequence": "XXY"}, "no axis twice in a row"),
    ({"columns": ["a", "b", "c"], "kind": "euler_deg", "sequence": "XyZ"}, "needs sequence"),
    ({"columns": ["a", "b", "c"], "kind": "rpy_deg", "sequence": "ZYX"}, "only for the euler kinds"),
])
def test_euler_sequence_is_checked_in_the_map(orientation, words):
    with pytest.raises(ValueError, match=words):
        OrientationMap(**orientation)
