"""Tests of D-optimal measurement-pose selection (hilcal.planning.design)."""

from __future__ import annotations

import copy
import itertools
import tomllib
from importlib import resources

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from hilcal.error_models import pose_difference
from hilcal.kinematics import Geometry, forward_kinematics, inverse_kinematics
from hilcal.planning import design as D
from hilcal.robot import Robot, default_robot, robot_from_dict


@pytest.fixture(scope="module")
def robot() -> Robot:
    return default_robot()


def _table1_dict() -> dict:
    return tomllib.loads(resources.files("hilcal.data").joinpath("paper_table1.toml").read_text())


def _uniform_box(robot: Robot, n: int, seed: int) -> np.ndarray:
    ws = robot.workspace
    return ws[:, 0] + np.random.default_rng(seed).random((n, 6)) * (ws[:, 1] - ws[:, 0])


def _leg_lengths_independent(robot: Robot, poses: np.ndarray) -> np.ndarray:
    """Joint-to-joint leg lengths from scipy's intrinsic Z-Y-X rotation (R = Rz(yaw) Ry(pitch) Rx(roll))."""
    R = Rotation.from_euler("ZYX", poses[:, [5, 4, 3]], degrees=True).as_matrix()
    platform = np.einsum("nij,kj->nki", R, robot.a) + poses[:, None, :3]
    return np.linalg.norm(platform - robot.b[None], axis=-1)


def _log_det_rebuilt(robot: Robot, poses: np.ndarray) -> float:
    sign, value = np.linalg.slogdet(D.information_matrix(robot, poses))
    assert sign > 0
    return float(value)


# --- feasibility ------------------------------------------------------------------------------------------


def test_home_is_feasible_and_each_box_face_is_enforced(robot: Robot) -> None:
    assert D.feasible(robot, robot.home)
    ws = robot.workspace
    for axis in range(6):
        for side, step in ((0, -1e-6), (1, 1e-6)):
            q = robot.home.copy()
            q[axis] = ws[axis, side] + step
            assert not D.feasible(robot, q), (axis, side)


def test_leg_limits_match_independently_computed_lengths(robot: Robot) -> None:
    poses = _uniform_box(robot, 3000, seed=7)
    lengths = _leg_lengths_independent(robot, poses)
    lo, hi = robot.leg_limits
    expected = np.all((lengths >= lo) & (lengths <= hi), axis=1)
    assert 0 < expected.sum() < len(poses), "the sample must contain both feasible and leg-limited poses"
    np.testing.assert_array_equal(D.feasible(robot, poses), expected)


def test_a_box_corner_beyond_the_leg_stroke_is_infeasible(robot: Robot) -> None:
    ws = robot.workspace
    corner = ws[:, 1].copy()
    lengths = _leg_lengths_independent(robot, corner[None])[0]
    assert lengths.max() > robot.leg_limits[1]
    assert not D.feasible(robot, corner)


def test_architecture_singular_robot_has_no_feasible_pose() -> None:
    # Similar planar base and platform hexagons: singular everywhere (Karger), legs are otherwise fine.
    data = copy.deepcopy(_table1_dict())
    for leg in data["legs"]:
        leg["a_mm"] = [0.4 * leg["b_mm"][0], 0.4 * leg["b_mm"][1], 0.0]
    data["leg_limits"] = {"min_mm": 3000.0, "max_mm": 4800.0}
    singular = robot_from_dict(data)
    poses = _uniform_box(singular, 200, seed=1)
    lengths = _leg_lengths_independent(singular, poses)
    legs_ok = np.all((lengths >= 3000.0) & (lengths <= 4800.0), axis=1)
    assert legs_ok.sum() > 100, "most poses must fail on the condition number alone"
    assert not D.feasible(singular, poses).any()
    with pytest.raises(ValueError, match="feasible"):
        D.random_poses(singular, 5, np.random.default_rng(0), max_draws=2000)


# --- random poses -------------------------------------------------------------------------------------------


def test_random_poses_are_feasible_seeded_and_cover_the_box(robot: Robot) -> None:
    a = D.random_poses(robot, 400, np.random.default_rng(3))
    b = D.random_poses(robot, 400, np.random.default_rng(3))
    c = D.random_poses(robot, 400, np.random.default_rng(4))
    assert a.shape == (400, 6)
    np.testing.assert_array_equal(a, b)
    assert not np.allclose(a, c)
    assert D.feasible(robot, a).all()
    ws = robot.workspace
    span = ws[:, 1] - ws[:, 0]
    assert np.all(a.min(axis=0) < ws[:, 0] + 0.1 * span)
    assert np.all(a.max(axis=0) > ws[:, 1] - 0.1 * span)


# --- information matrix ---------------------------------------------------------------------------------


def test_information_matrix_matches_finite_difference_jacobian(robot: Robot) -> None:
    poses = np.array(
        [
            [0.0, 0.0, 3091.2, 0.0, 0.0, 0.0],
            [150.0, -80.0, 3000.0, 4.0, -3.0, 6.0],
            [-200.0, 120.0, 3250.0, -5.0, 6.0, -8.0],
        ]
    )
    nominal = Geometry.nominal(robot)
    legs = inverse_kinematics(nominal, poses)
    length_mm = robot.characteristic_length_mm
    h = 1e-3
    columns = []
    for j in range(D.N_PARAMETERS):
        dp = np.zeros(D.N_PARAMETERS)
        dp[j] = h
        plus = forward_kinematics(nominal.perturbed(dp), legs, poses)
        minus = forward_kinematics(nominal.perturbed(-dp), legs, poses)
        diff = pose_difference(plus, poses, length_mm) - pose_difference(minus, poses, length_mm)
        columns.append(diff / (2 * h))
    J_fd = np.stack(columns, axis=-1)  # (3, 6, 42)
    M_fd = np.einsum("kij,kil->jl", J_fd, J_fd)
    M = D.information_matrix(robot, poses)
    assert M.shape == (42, 42)
    np.testing.assert_allclose(M, M_fd, rtol=1e-5, atol=1e-6 * np.abs(M_fd).max())


def test_rank6_exchange_gives_the_same_log_det_as_rebuilding(robot: Robot) -> None:
    poses = D.random_poses(robot, 12, np.random.default_rng(11))
    candidates = D.random_poses(robot, 5, np.random.default_rng(12))
    M = D.information_matrix(robot, poses)
    J = D.pose_jacobians(robot, poses)
    k = 4
    got = D.candidate_log_dets(M, J[k], D.pose_jacobians(robot, candidates))
    expected = []
    for c in candidates:
        swapped = poses.copy()
        swapped[k] = c
        expected.append(_log_det_rebuilt(robot, swapped))
    np.testing.assert_allclose(got, expected, rtol=0, atol=1e-8)
    added = D.candidate_log_dets(M, None, D.pose_jacobians(robot, candidates[:1]))
    np.testing.assert_allclose(
        added, [_log_det_rebuilt(robot, np.vstack([poses, candidates[:1]]))], atol=1e-8
    )


# --- metrics ------------------------------------------------------------------------------------------------


def test_design_metrics_are_per_pose_and_consistent(robot: Robot) -> None:
    poses = D.random_poses(robot, 16, np.random.default_rng(5))
    m = D.design_metrics(robot, poses)
    assert m.n_poses == 16 and m.d_efficiency is None
    assert m.log_det == pytest.approx(_log_det_rebuilt(robot, poses) - 42 * np.log(16), abs=1e-8)
    # Borm–Menq O1 = (prod sigma)^(1/42) / sqrt(n) = det(M/n)^(1/84).
    assert m.observability_index == pytest.approx(np.exp(m.log_det / 84), rel=1e-8)
    A = D.pose_jacobians(robot, poses).reshape(-1, 42)
    assert m.min_singular_value == pytest.approx(np.linalg.svd(A, compute_uv=False)[-1], rel=1e-10)
    # Condition number does not depend on how the parameters are scaled.
    scaled = A * np.random.default_rng(0).uniform(0.1, 10.0, 42)
    s = np.linalg.svd(scaled / np.linalg.norm(scaled, axis=0), compute_uv=False)
    assert m.condition_number == pytest.approx(s[0] / s[-1], rel=1e-8)
    # Repeating every pose doubles M but leaves the per-pose information (and D-efficiency) unchanged.
    twice = D.design_metrics(robot, np.vstack([poses, poses]), reference_log_det_per_pose=m.log_det)
    assert twice.n_poses == 32
    assert twice.d_efficiency == pytest.approx(1.0, abs=1e-9)


def test_too_few_poses_are_rejected(robot: Robot) -> None:
    with pytest.raises(ValueError, match="at least 7"):
        D.coordinate_exchange(robot, 6, np.random.default_rng(0))
    with pytest.raises(ValueError, match="not feasible"):
        D.coordinate_exchange(
            robot, 8, np.random.default_rng(0), start=np.tile(robot.workspace[:, 1], (8, 1))
        )


# --- coordinate exchange -----------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def exchanged(robot: Robot) -> tuple[np.ndarray, D.Design]:
    start = D.random_poses(robot, 16, np.random.default_rng(21))
    return start, D.coordinate_exchange(robot, 16, np.random.default_rng(0), start=start)


def test_coordinate_exchange_beats_its_random_start(robot: Robot, exchanged) -> None:
    start, design = exchanged
    assert design.poses.shape == (16, 6)
    assert D.feasible(robot, design.poses).all()
    ref = D.design_metrics(robot, start).log_det
    assert design.metrics.log_det > ref
    metrics = D.design_metrics(robot, design.poses, reference_log_det_per_pose=ref)
    assert metrics.d_efficiency > 1.5
    assert metrics.condition_number < D.design_metrics(robot, start).condition_number
    assert design.converged and design.n_passes >= 2
    assert len(np.unique(design.poses, axis=0)) == 16, "poses must be distinct by default"


def test_coordinate_exchange_ends_at_a_coordinatewise_optimum(robot: Robot, exchanged) -> None:
    _, design = exchanged
    final = _log_det_rebuilt(robot, design.poses)
    ws = robot.workspace
    for k in (0, 7):
        for axis in range(6):
            for value in np.linspace(ws[axis, 0], ws[axis, 1], 11):
                trial = design.poses.copy()
                trial[k, axis] = value
                duplicate = np.any(np.all(np.delete(trial, k, axis=0) == trial[k], axis=1))
                if D.feasible(robot, trial[k]) and not duplicate:
                    assert _log_det_rebuilt(robot, trial) <= final + 1e-5, (k, axis, value)


def test_coordinate_exchange_is_seeded(robot: Robot) -> None:
    a = D.coordinate_exchange(robot, 8, np.random.default_rng(9), max_passes=2)
    b = D.coordinate_exchange(robot, 8, np.random.default_rng(9), max_passes=2)
    np.testing.assert_array_equal(a.poses, b.poses)
    assert a.n_passes <= 2


# --- factorial exchange, paper sets, verification -------------------------------------------------------


def test_factorial_candidates_are_the_feasible_grid_points(robot: Robot) -> None:
    ws = robot.workspace
    grid = np.array(list(itertools.product(*[(lo, (lo + hi) / 2, hi) for lo, hi in ws])))
    lengths = _leg_lengths_independent(robot, grid)
    lo, hi = robot.leg_limits
    expected = grid[np.all((lengths >= lo) & (lengths <= hi), axis=1)]
    np.testing.assert_allclose(D.factorial_candidates(robot, 3), expected)


@pytest.fixture(scope="module")
def paper_sets(robot: Robot) -> dict[str, D.Design]:
    return D.paper_pose_sets(robot, seed=2022)


@pytest.mark.slow
def test_one_paper_pose_set_alone_is_the_same_as_among_all_four(robot: Robot, paper_sets) -> None:
    """`hilcal identifiability` makes only the set it analyses: it must be the one the four-set call makes. Set 2 is
    the one that could differ (it draws from set 1's stream after it); sets 3 and 4 use no shared stream."""
    key = "set2_doptimal32"
    alone = D.paper_pose_sets(robot, seed=2022, names=[key])
    assert list(alone) == [key]
    np.testing.assert_array_equal(alone[key].poses, paper_sets[key].poses)
    assert alone[key].metrics.d_efficiency == pytest.approx(paper_sets[key].metrics.d_efficiency, rel=1e-12)
    with pytest.raises(ValueError, match="unknown pose set"):
        D.paper_pose_sets(robot, seed=2022, names=["set5"])


@pytest.mark.slow
def test_paper_pose_sets_are_feasible_and_better_than_random(robot: Robot, paper_sets) -> None:
    assert list(paper_sets) == [
        "set1_random32",
        "set2_doptimal32",
        "set3_factorial_exchange32",
        "set4_doptimal64",
    ]
    for key, design in paper_sets.items():
        assert design.name == key
        assert D.feasible(robot, design.poses).all(), key
        assert len(np.unique(design.poses, axis=0)) == design.metrics.n_poses, key
    assert paper_sets["set1_random32"].metrics.d_efficiency == pytest.approx(1.0)
    for key in ("set2_doptimal32", "set3_factorial_exchange32", "set4_doptimal64"):
        assert paper_sets[key].metrics.d_efficiency > 1.5, key
    assert paper_sets["set4_doptimal64"].metrics.n_poses == 64


@pytest.mark.slow
def test_design_report_lists_every_design(paper_sets) -> None:
    report = D.design_report(paper_sets)
    lines = report.splitlines()
    assert len(lines) == 2 + len(paper_sets)
    for key, design in paper_sets.items():
        row = next(line for line in lines if line.startswith(key))
        assert f"{design.metrics.d_efficiency:.3f}" in row


def test_verification_poses_are_feasible_seeded_and_spread(robot: Robot) -> None:
    poses = D.verification_poses(robot, 24, seed=1)
    assert poses.shape == (24, 6)
    assert D.feasible(robot, poses).all()
    np.testing.assert_array_equal(poses, D.verification_poses(robot, 24, seed=1))
    assert not np.allclose(poses, D.verification_poses(robot, 24, seed=2))
    ws = robot.workspace
    unit = (poses - ws[:, 0]) / (ws[:, 1] - ws[:, 0])
    d = np.linalg.norm(unit[:, None] - unit[None], axis=-1)[np.triu_indices(24, 1)]
    # 24 uniform points in the unit 6-cube have a median minimum distance near 0.31.
    assert d.min() > 0.4
