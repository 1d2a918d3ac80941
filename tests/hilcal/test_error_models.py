"""Error-model Jacobians against finite differences of the nonlinear kinematics, and the paper's 60 model."""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from hilcal.error_models import (
    forward_jacobian,
    implicit_jacobian,
    implicit_residuals,
    paper60_jacobian,
    pose_difference,
    rotation_vector,
)
from hilcal.kinematics import Geometry, forward_kinematics, inverse_kinematics
from tests.poses import feasible_random_poses

LC = 1400.0


def test_rotation_vector_matches_scipy(rng):
    axes = rng.normal(size=(20, 3))
    axes /= np.linalg.norm(axes, axis=1)[:, None]
    rv = axes * np.array([[1e-9], [1e-3], [1.0], [3.0]] * 5)
    R = Rotation.from_rotvec(rv).as_matrix()
    np.testing.assert_allclose(rotation_vector(R), rv, atol=1e-12)


def test_forward_jacobian_matches_finite_differences(robot, rng):
    nominal = Geometry.nominal(robot)
    poses = feasible_random_poses(robot, 6, rng)
    lengths = inverse_kinematics(nominal, poses)
    J = forward_jacobian(nominal, poses, LC)
    h = 1e-4
    for j in range(42):
        dp = np.zeros(42)
        dp[j] = h
        plus = forward_kinematics(nominal.perturbed(dp), lengths, poses)
        minus = forward_kinematics(nominal.perturbed(-dp), lengths, poses)
        fd = pose_difference(plus, minus, LC) / (2 * h)
        np.testing.assert_allclose(J[:, :, j], fd, atol=1e-6)


def test_implicit_jacobian_matches_finite_differences(robot, rng):
    nominal = Geometry.nominal(robot)
    poses = feasible_random_poses(robot, 4, rng)
    legs = inverse_kinematics(nominal, poses) + rng.normal(0, 0.01, (4, 6))
    J = implicit_jacobian(nominal, poses)
    h = 1e-4
    for j in range(42):
        dp = np.zeros(42)
        dp[j] = h
        fd = (implicit_residuals(nominal.perturbed(dp), legs, poses)
              - implicit_residuals(nominal.perturbed(-dp), legs, poses)) / (2 * h)
        np.testing.assert_allclose(J[:, :, j], fd, atol=1e-8)


def test_linear_model_predicts_pose_error_of_true_robot(robot, rng):
    nominal = Geometry.nominal(robot)
    poses = feasible_random_poses(robot, 20, rng)
    dp = rng.normal(0.0, 0.5, 42)
    true_poses = forward_kinematics(nominal.perturbed(dp), inverse_kinematics(nominal, poses), poses)
    actual = pose_difference(true_poses, poses, LC)
    predicted = forward_jacobian(nominal, poses, LC) @ dp
    assert np.abs(actual - predicted).max() < 0.01 * np.abs(actual).max()


def test_common_base_shift_is_a_pure_translation_in_both_models(robot, rng):
    nominal = Geometry.nominal(robot)
    poses = feasible_random_poses(robot, 5, rng)
    shift = np.array([0.3, -0.2, 0.1])
    dp42 = np.zeros((6, 7))
    dp42[:, 3:6] = shift
    dp60 = np.zeros((6, 10))
    dp60[:, 7:10] = shift
    expected = np.concatenate([shift, np.zeros(3)])
    np.testing.assert_allclose(forward_jacobian(nominal, poses, LC) @ dp42.ravel(), np.tile(expected, (5, 1)),
                               atol=1e-10)
    np.testing.assert_allclose(paper60_jacobian(nominal, poses, LC) @ dp60.ravel(), np.tile(expected, (5, 1)),
                               atol=1e-10)


def test_paper60_with_zero_du_misrepresents_a_rigid_robot(robot, rng):
    # The paper's eq. 23 treats each vector chain as a rigid 3-D constraint; a real leg pivots freely, so a
    # pure leg-length error moves the platform differently from what the 60-parameter model predicts.
    nominal = Geometry.nominal(robot)
    poses = feasible_random_poses(robot, 10, rng)
    dl = np.zeros((6, 10))
    dl[0, 0] = 1.0
    rigid = np.zeros((6, 7))
    rigid[0, 6] = 1.0
    truth = pose_difference(
        forward_kinematics(nominal.perturbed(rigid.ravel()), inverse_kinematics(nominal, poses), poses), poses, LC)
    paper = paper60_jacobian(nominal, poses, LC) @ dl.ravel()
    assert np.abs(truth - paper).max() > 0.2 * np.abs(truth).max()
