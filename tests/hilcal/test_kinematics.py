"""Kinematics: rotation convention, IK, FK round trip, Jacobians against finite differences, statics."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from hilcal.kinematics import (
    ForwardKinematicsError,
    Geometry,
    SingularPoseError,
    forward_kinematics,
    gravity_wrench,
    inverse_jacobian,
    inverse_kinematics,
    leg_forces,
    pose_jacobian,
    rpy_rate_matrix,
    split_pose,
)
from hilcal.robot import rotation_matrix
from tests.poses import feasible_random_poses


def test_rotation_matrix_matches_paper_eq2_with_typo_fixed(rng):
    roll, pitch, yaw = rng.uniform(-0.5, 0.5, 3)
    R = rotation_matrix(np.array([roll, pitch, yaw]))
    reference = Rotation.from_euler("ZYX", [yaw, pitch, roll]).as_matrix()
    np.testing.assert_allclose(R, reference, atol=1e-15)
    cf, sf, ct, st, cp, sp = np.cos(roll), np.sin(roll), np.cos(pitch), np.sin(pitch), np.cos(yaw), np.sin(yaw)
    # eq. (2) element (1,2) read as cos(psi) sin(theta) sin(phi) - sin(psi) cos(phi), not ... sin(theta) sin(theta) ...
    assert R[0, 1] == pytest.approx(cp * st * sf - sp * cf, abs=1e-15)
    assert R[2, 1] == pytest.approx(ct * sf, abs=1e-15)


def test_inverse_kinematics_is_the_leg_vector_norm(robot):
    pose = np.array([120.0, -80.0, 3000.0, 3.0, -2.0, 5.0])
    R = Rotation.from_euler("ZYX", pose[[5, 4, 3]], degrees=True).as_matrix()
    expected = [np.linalg.norm(R @ robot.a[i] + pose[:3] - robot.b[i]) for i in range(6)]
    np.testing.assert_allclose(inverse_kinematics(Geometry.nominal(robot), pose), expected, rtol=1e-14)


def test_ik_fk_round_trip_10000_poses(robot, rng):
    geom = Geometry.nominal(robot)
    poses = feasible_random_poses(robot, 10_000, rng)
    solved = forward_kinematics(geom, inverse_kinematics(geom, poses), robot.home)
    assert np.abs(solved[:, :3] - poses[:, :3]).max() < 1e-8
    assert np.abs(solved[:, 3:] - poses[:, 3:]).max() < 1e-9


def test_fk_with_geometric_errors_satisfies_leg_equations(robot, rng):
    geom = Geometry.nominal(robot).perturbed(rng.normal(0.0, 1.0, 42))
    lengths = inverse_kinematics(Geometry.nominal(robot), feasible_random_poses(robot, 50, rng))
    poses = forward_kinematics(geom, lengths, robot.home)
    R, t = split_pose(poses)
    for k in range(len(poses)):
        geometric = np.linalg.norm(R[k] @ geom.a.T + t[k][:, None] - geom.b.T, axis=0)
        np.testing.assert_allclose(geometric, lengths[k] + geom.dl0, atol=1e-9)


def test_pose_jacobian_matches_finite_differences(robot, rng):
    geom = Geometry.nominal(robot)
    poses = feasible_random_poses(robot, 5, rng)
    J = pose_jacobian(geom, poses)
    for k in range(6):
        h = np.zeros(6)
        h[k] = 1e-3 if k < 3 else np.degrees(1e-6)
        step = 1e-3 if k < 3 else 1e-6
        fd = (inverse_kinematics(geom, poses + h) - inverse_kinematics(geom, poses - h)) / (2 * step)
        np.testing.assert_allclose(J[:, :, k], fd, rtol=1e-6, atol=1e-7)


def test_rpy_rate_matrix_maps_angle_rates_to_angular_velocity(rng):
    rpy = rng.uniform(-0.3, 0.3, 3)
    d = rng.normal(size=3) * 1e-7
    R0, R1 = rotation_matrix(rpy), rotation_matrix(rpy + d)
    W = (R1 - R0) @ R0.T
    omega = np.array([W[2, 1], W[0, 2], W[1, 0]])
    np.testing.assert_allclose(omega, rpy_rate_matrix(rpy) @ d, rtol=1e-5, atol=1e-14)


def test_unreachable_lengths_raise(robot):
    with pytest.raises(ForwardKinematicsError) as info:
        forward_kinematics(Geometry.nominal(robot), np.full((2, 6), 100.0), robot.home)
    assert info.value.indices.tolist() == [0, 1]


def test_singular_pose_raises(robot):
    # With the platform in the base plane every leg is horizontal: nothing resists a vertical motion.
    flat = Geometry(robot.a, robot.a * 2.0)
    pose = np.array([0.0, 0.0, 0.0, 0.0, 0.0, 0.0])
    with pytest.raises(SingularPoseError):
        forward_kinematics(flat, inverse_kinematics(flat, pose), pose)


def test_the_singularity_check_names_exactly_the_rows_past_the_limit(robot, rng):
    """Against the singular values computed here: with the limit at the median condition number, the error names
    every pose at or above it and no other, with the first one's condition."""
    geom = Geometry.nominal(robot)
    poses = feasible_random_poses(robot, 40, rng)
    R, t = split_pose(poses)
    J = inverse_jacobian(geom, R, t)
    J[..., 3:] /= np.sqrt(np.mean(np.sum((robot.a - robot.a.mean(axis=0)) ** 2, axis=1)))
    s = np.linalg.svd(J, compute_uv=False)
    cond = s[:, 0] / s[:, -1]
    limit = float(np.median(cond))
    with pytest.raises(SingularPoseError) as info:
        forward_kinematics(geom, inverse_kinematics(geom, poses), poses, max_condition=limit)
    assert info.value.indices.tolist() == np.flatnonzero(cond >= limit).tolist()
    assert f"condition {cond[cond >= limit][0]:.3g}" in str(info.value)
    assert forward_kinematics(geom, inverse_kinematics(geom, poses), poses, max_condition=1.01 * cond.max()).shape == (
        40, 6)


def test_gravity_leg_forces_balance_the_weight(robot, rng):
    geom = Geometry.nominal(robot)
    poses = feasible_random_poses(robot, 20, rng)
    forces = leg_forces(geom, poses, gravity_wrench(robot, poses))
    R, t = split_pose(poses)
    weight = robot.moving_mass_kg * robot.gravity_mps2
    for k in range(len(poses)):
        ra = (R[k] @ robot.a.T).T
        u = ra + t[k] - robot.b
        u /= np.linalg.norm(u, axis=1)[:, None]
        push = forces[k][:, None] * u
        np.testing.assert_allclose(push.sum(axis=0), [0.0, 0.0, weight], atol=1e-6 * weight)
        com = R[k] @ robot.com
        moment = np.cross(ra, push).sum(axis=0) + np.cross(com, [0.0, 0.0, -weight])
        np.testing.assert_allclose(moment, 0.0, atol=1e-6 * weight * 1000)
    home = leg_forces(geom, robot.home, gravity_wrench(robot, robot.home))
    assert (home > 0).all(), "the legs carry the platform in compression"
