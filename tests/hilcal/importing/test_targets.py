"""Poses from raw target points: the CMM path's registration, with and without base targets."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from hilcal.importing.errors import ValueProblem
from hilcal.importing.targets import register_targets
from hilcal.pose_measurement import pose_from_spheres
from tests.poses import feasible_random_poses as random_poses


def _place(pose: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Points of a body (K, 3) at poses (n, 6), by scipy's ZYX rotation (an independent implementation)."""
    rot = Rotation.from_euler("ZYX", pose[:, [5, 4, 3]], degrees=True)
    return np.stack([rot.apply(p) for p in points], axis=1) + pose[:, None, :3]


def test_noise_free_targets_in_the_base_frame_give_the_pose(robot, rng):
    poses = random_poses(robot, 30, rng)
    fit = register_targets(_place(poses, robot.platform_spheres), robot.platform_spheres)
    np.testing.assert_allclose(fit.pose, poses, atol=1e-9)
    assert fit.base_rms_mm is None and np.all(fit.rms_mm < 1e-9)


def test_with_base_targets_the_instrument_frame_cancels_exactly_as_in_the_cmm_path(robot, rng):
    poses = random_poses(robot, 30, rng)
    tracker = np.array([[1500.0, -2500.0, 400.0, 1.5, -2.0, 140.0]])
    to_tracker = Rotation.from_euler("ZYX", tracker[0, [5, 4, 3]], degrees=True).inv()
    platform = to_tracker.apply((_place(poses, robot.platform_spheres) - tracker[0, :3]).reshape(-1, 3))
    platform = platform.reshape(30, -1, 3) + rng.normal(0, 0.005, (30, 3, 3))
    base = to_tracker.apply(robot.base_spheres - tracker[0, :3]) + rng.normal(0, 0.005, (30, 3, 3))
    fit = register_targets(platform, robot.platform_spheres, base, robot.base_spheres)
    cmm = pose_from_spheres(platform, base, robot)
    np.testing.assert_allclose(fit.pose, cmm.pose, atol=1e-9)
    np.testing.assert_allclose(fit.rms_mm, np.max(cmm.rms_residual_mm, axis=1), atol=1e-12)
    assert np.abs(fit.pose - poses).max() < 0.05


def test_points_in_metres_read_as_mm_name_the_worst_target(robot, rng):
    poses = random_poses(robot, 4, rng)
    points = _place(poses, robot.platform_spheres)
    points[3] /= 1000.0
    with pytest.raises(ValueProblem) as info:
        register_targets(points, robot.platform_spheres)
    assert info.value.row == 3 and "do not fit their layout" in str(info.value)
    moved = _place(poses, robot.platform_spheres)
    moved[1, 2] += 60.0
    with pytest.raises(ValueProblem) as info:
        register_targets(moved, robot.platform_spheres)
    assert (info.value.row, info.value.column) == (1, 2)
