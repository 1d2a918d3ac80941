"""ISO 9283 AP and RP against hand-worked examples from the standard's definitions, the test cube and P1-P5.

Every expected number below is worked out by hand in the comments (barycentre, distances, sample standard
deviations), never taken from the code under test.
"""

from __future__ import annotations

import numpy as np
import pytest

from hilcal.acceptance.iso9283 import CYCLE_ORDER, cycle_route, iso_poses, largest_cube, pose_characteristics
from hilcal.robot import Robot
from hilcal.workspace import feasible


def test_ap_rp_of_three_cycles_along_x_by_hand() -> None:
    # Commanded (0, 0, 0); attained x = 1, 2, 3 mm. Barycentre x̄ = 2 -> AP_x = 2, AP_P = 2 mm.
    # l_j = |x_j - 2| = 1, 0, 1 -> l̄ = 2/3; S_l = sqrt(((1/3)² + (2/3)² + (1/3)²) / 2) = sqrt(1/3).
    # RP_l = 2/3 + 3 sqrt(1/3) = 2.398717... Roll a = 0.1, 0.3, 0.2 deg: ā = 0.2 -> AP_a = 0.2 deg;
    # S_a = sqrt((0.01 + 0.01 + 0) / 2) = 0.1 -> RP_a = 3 S_a = 0.3 deg.
    attained = np.array([[1.0, 0, 0, 0.1, 0, 0], [2.0, 0, 0, 0.3, 0, 0], [3.0, 0, 0, 0.2, 0, 0]])
    ch = pose_characteristics(attained, np.zeros(6))
    assert ch.n_cycles == 3
    np.testing.assert_allclose(ch.ap_xyz_mm, [2.0, 0.0, 0.0], atol=1e-12)
    assert ch.ap_p_mm == pytest.approx(2.0)
    np.testing.assert_allclose(ch.l_mm, [1.0, 0.0, 1.0], atol=1e-12)
    assert ch.l_mean_mm == pytest.approx(2.0 / 3.0)
    assert ch.s_l_mm == pytest.approx(np.sqrt(1.0 / 3.0))
    assert ch.rp_l_mm == pytest.approx(2.0 / 3.0 + 3.0 * np.sqrt(1.0 / 3.0))
    assert ch.rp_l_mm == pytest.approx(2.398717, abs=1e-6)
    np.testing.assert_allclose(ch.ap_abc_deg, [0.2, 0.0, 0.0], atol=1e-12)
    np.testing.assert_allclose(ch.rp_abc_deg, [0.3, 0.0, 0.0], atol=1e-12)


def test_ap_rp_of_four_cycles_in_space_by_hand() -> None:
    # Commanded (10, 20, 30). Attained positions: the commanded one offset by (1, 1, 0) plus (±3, 0, 0) and
    # (0, ±4, 0): barycentre (11, 21, 30) -> AP = (1, 1, 0), AP_P = sqrt(2). l_j = 3, 3, 4, 4 -> l̄ = 3.5,
    # S_l = sqrt(4 * 0.25 / 3) = sqrt(1/3) -> RP_l = 3.5 + sqrt(3) = 5.232051.
    # Yaw c = 1, 1, 1, 5 deg, commanded 0: c̄ = 2 -> AP_c = 2; S_c = sqrt((1 + 1 + 1 + 9) / 3) = 2 -> RP_c = 6.
    base = np.array([11.0, 21.0, 30.0])
    offsets = np.array([[3.0, 0, 0], [-3.0, 0, 0], [0, 4.0, 0], [0, -4.0, 0]])
    attained = np.hstack([base + offsets, np.zeros((4, 2)), np.array([[1.0], [1.0], [1.0], [5.0]])])
    ch = pose_characteristics(attained, np.array([10.0, 20.0, 30.0, 0.0, 0.0, 0.0]))
    assert ch.ap_p_mm == pytest.approx(np.sqrt(2.0))
    np.testing.assert_allclose(ch.l_mm, [3.0, 3.0, 4.0, 4.0])
    assert ch.rp_l_mm == pytest.approx(5.232051, abs=1e-6)
    assert ch.ap_abc_deg[2] == pytest.approx(2.0)
    assert ch.rp_abc_deg[2] == pytest.approx(6.0)


def test_angles_across_plus_minus_180_degrees_average_correctly() -> None:
    # Yaw 179 and -179 deg around a command of 180: the attained yaws are 1 deg either side -> AP_c = 0, S_c =
    # sqrt(2) -> RP_c = 3 sqrt(2); a naive mean of 179 and -179 would be 0, 180 deg off.
    attained = np.array([[0, 0, 0, 0, 0, 179.0], [0, 0, 0, 0, 0, -179.0]])
    ch = pose_characteristics(attained, np.array([0, 0, 0, 0, 0, 180.0]))
    assert ch.ap_abc_deg[2] == pytest.approx(0.0, abs=1e-9)
    assert ch.rp_abc_deg[2] == pytest.approx(3.0 * np.sqrt(2.0))


def test_one_cycle_has_no_repeatability() -> None:
    with pytest.raises(ValueError, match="two cycles"):
        pose_characteristics(np.zeros((1, 6)), np.zeros(6))


def test_p1_to_p5_on_the_diagonal_plane_of_the_largest_cube(robot: Robot) -> None:
    cube = largest_cube(robot, lower_margin_mm=3.0)
    ws = robot.workspace
    np.testing.assert_allclose(cube.centre_mm, ws[:3].mean(axis=1))
    P = iso_poses(cube)
    a = cube.side_mm
    np.testing.assert_allclose(P[0, :3], cube.centre_mm)
    # P2..P5: 10 % of the diagonal (a sqrt 3) from C1 (-,-,-), C2 (+,-,-), C7 (+,+,+), C8 (-,+,+) towards
    # the opposite corner, i.e. 0.4 a from the centre along each axis.
    signs = np.array([[-1, -1, -1], [1, -1, -1], [1, 1, 1], [-1, 1, 1]], dtype=float)
    np.testing.assert_allclose(P[1:, :3], cube.centre_mm + 0.4 * a * signs, atol=1e-9)
    corners = cube.centre_mm + 0.5 * a * signs
    np.testing.assert_allclose(np.linalg.norm(P[1:, :3] - corners, axis=1), 0.1 * a * np.sqrt(3.0), rtol=1e-12)
    d = P[:, :3] - cube.centre_mm
    np.testing.assert_allclose(d[:, 1], d[:, 2], atol=1e-9)  # all in the diagonal plane y = z
    np.testing.assert_allclose(P[:, 3:], np.broadcast_to(robot.home[3:], (5, 3)))


def test_the_cube_is_the_largest_that_fits(robot: Robot) -> None:
    """Every corner is reachable; a cube 2 % larger either leaves the workspace box or is not reachable."""
    cube = largest_cube(robot, lower_margin_mm=3.0)
    signs = np.array(np.meshgrid([-1, 1], [-1, 1], [-1, 1], indexing="ij")).reshape(3, -1).T
    orientation = np.broadcast_to(cube.orientation_deg, (8, 3))

    def corners(side: float) -> np.ndarray:
        return np.hstack([cube.centre_mm + 0.5 * side * signs, orientation])

    assert feasible(robot, corners(cube.side_mm)).all()
    assert not feasible(robot, corners(1.02 * cube.side_mm)).all()


def test_a_small_leg_stroke_makes_a_smaller_cube(robot: Robot) -> None:
    """A robot whose legs cannot reach the whole workspace box gets a cube limited by its legs, not by the box."""
    lo, hi = robot.leg_limits
    tight = Robot(robot.spec.model_copy(update={"leg_limits": robot.spec.leg_limits.model_copy(
        update={"min_mm": 4200.0, "max_mm": 4400.0})}))
    assert (lo, hi) != tight.leg_limits
    small = largest_cube(tight)
    assert 0 < small.side_mm < largest_cube(robot).side_mm
    grid = np.linspace(-0.5, 0.5, 5) * small.side_mm
    xyz = np.stack(np.meshgrid(grid, grid, grid, indexing="ij"), axis=-1).reshape(-1, 3) + small.centre_mm
    assert feasible(tight, np.hstack([xyz, np.broadcast_to(small.orientation_deg, (len(xyz), 3))])).all()


def test_cycles_visit_p1_p5_p4_p3_p2(robot: Robot) -> None:
    P = iso_poses(largest_cube(robot))
    rows, which = cycle_route(P, 2)
    assert CYCLE_ORDER == (0, 4, 3, 2, 1)
    assert which.tolist() == [0, 4, 3, 2, 1, 0, 4, 3, 2, 1]
    np.testing.assert_array_equal(rows, P[which])
