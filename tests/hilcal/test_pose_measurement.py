"""Pose from measured sphere centres and from any two point layouts (a laser tracker's targets): exact recovery,
instrument-frame invariance and noise propagation."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from hilcal.pose_measurement import pose_from_matrix, pose_from_points, pose_from_spheres, rigid_fit
from hilcal.robot import default_robot, rotation_matrix

ROBOT = default_robot()


def random_pose(rng: np.random.Generator) -> np.ndarray:
    return np.concatenate(
        [rng.uniform([-400, -400, 2800], [400, 400, 3400]), rng.uniform([-60, -60, -170], [60, 60, 170])]
    )


def spheres_in_cmm(pose: np.ndarray, cmm_rot: np.ndarray, cmm_t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Sphere centres in a CMM frame given by p_cmm = cmm_rot p_base + cmm_t (built from rotation_matrix)."""
    R = rotation_matrix(np.radians(pose[3:]))
    platform_base = ROBOT.platform_spheres @ R.T + pose[:3]
    return platform_base @ cmm_rot.T + cmm_t, ROBOT.base_spheres @ cmm_rot.T + cmm_t


def random_cmm(rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    return Rotation.random(random_state=rng).as_matrix(), rng.uniform(-5000, 5000, 3)


def test_pose_from_matrix_inverts_rotation_matrix() -> None:
    rng = np.random.default_rng(0)
    rpy = rng.uniform([-179, -89, -179], [179, 89, 179], (100, 3))
    t = rng.normal(size=(100, 3))
    pose = pose_from_matrix(rotation_matrix(np.radians(rpy)), t)
    np.testing.assert_allclose(pose[:, 3:], rpy, atol=1e-9)
    np.testing.assert_array_equal(pose[:, :3], t)
    # a quarter turn about z alone is yaw 90 degrees
    Rz = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    np.testing.assert_allclose(pose_from_matrix(Rz, np.zeros(3)), [0, 0, 0, 0, 0, 90], atol=1e-12)


def test_exact_recovery_with_arbitrary_cmm_placement() -> None:
    rng = np.random.default_rng(1)
    for _ in range(50):
        pose = random_pose(rng)
        fit = pose_from_spheres(*spheres_in_cmm(pose, *random_cmm(rng)), ROBOT)
        assert np.max(np.abs(fit.pose[:3] - pose[:3])) < 1e-9
        assert np.max(np.abs(fit.pose[3:] - pose[3:])) < 1e-9
        assert np.all(fit.rms_residual_mm < 1e-9)


def test_invariant_to_the_cmm_frame() -> None:
    rng = np.random.default_rng(2)
    pose = random_pose(rng)
    noise = rng.normal(0.0, 0.02, (2, 3, 3))
    fits = []
    for _ in range(5):
        cmm_rot, cmm_t = random_cmm(rng)
        platform, base = spheres_in_cmm(pose, cmm_rot, cmm_t)
        # the same physical measurement errors (given in the base frame) seen from each CMM placement
        fits.append(pose_from_spheres(platform + noise[0] @ cmm_rot.T, base + noise[1] @ cmm_rot.T, ROBOT))
    for fit in fits[1:]:
        np.testing.assert_allclose(fit.pose, fits[0].pose, atol=1e-9)
        np.testing.assert_allclose(fit.rms_residual_mm, fits[0].rms_residual_mm, atol=1e-9)
    assert np.all(fits[0].rms_residual_mm > 1e-4)


def test_batch_matches_single_measurements() -> None:
    rng = np.random.default_rng(3)
    cmm = random_cmm(rng)
    pairs = [spheres_in_cmm(random_pose(rng), *cmm) for _ in range(7)]
    platform = np.array([p for p, _ in pairs]) + rng.normal(0, 0.01, (7, 3, 3))
    base = np.array([b for _, b in pairs]) + rng.normal(0, 0.01, (7, 3, 3))
    batch = pose_from_spheres(platform, base, ROBOT)
    assert batch.pose.shape == (7, 6) and batch.rms_residual_mm.shape == (7, 2)
    for k in range(7):
        single = pose_from_spheres(platform[k], base[k], ROBOT)
        np.testing.assert_allclose(batch.pose[k], single.pose, atol=1e-9)
        np.testing.assert_allclose(batch.rms_residual_mm[k], single.rms_residual_mm, atol=1e-12)


def test_noise_propagation_is_of_the_order_of_the_sphere_noise() -> None:
    sigma = 0.01
    rng = np.random.default_rng(4)
    pose = np.array([120.0, -80.0, 3200.0, 3.0, -2.0, 5.0])
    platform, base = spheres_in_cmm(pose, *random_cmm(rng))
    n = 2000
    fit = pose_from_spheres(platform + rng.normal(0, sigma, (n, 3, 3)), base + rng.normal(0, sigma, (n, 3, 3)), ROBOT)
    pos_std = fit.pose[:, :3].std(axis=0)
    assert np.all(pos_std > 0.2 * sigma) and np.all(pos_std < 3 * sigma)
    assert np.max(np.abs(fit.pose[:, :3].mean(axis=0) - pose[:3])) < 5 * 3 * sigma / np.sqrt(n)
    # rotation noise ~ sigma / (sphere radius ~1000 mm) rad
    ang_std_rad = np.radians(fit.pose[:, 3:].std(axis=0))
    assert np.all(ang_std_rad < 10 * sigma / 1000.0) and np.all(ang_std_rad > 0.1 * sigma / 3000.0)
    # 3 spheres give 9 coordinates, 6 are absorbed by the fit: 3 sigma^2 of squared residual, sigma^2 per sphere
    rms = np.sqrt(np.mean(fit.rms_residual_mm**2, axis=0))
    np.testing.assert_allclose(rms, sigma, rtol=0.1)


def test_a_displaced_sphere_shows_in_its_registration_residual() -> None:
    platform, base = spheres_in_cmm(np.array([0.0, 0.0, 3091.2, 0.0, 0.0, 0.0]), np.eye(3), np.zeros(3))
    platform[1] += 0.9 * np.array([-0.5, 0.866, 0.0])  # stretches the triangle: no rigid motion absorbs it
    fit = pose_from_spheres(platform, base, ROBOT)
    assert fit.platform_rms_mm > 0.1 and fit.base_rms_mm < 1e-9


def test_rigid_fit_returns_a_proper_rotation_for_a_mirrored_layout() -> None:
    model = ROBOT.platform_spheres
    R, _, _ = rigid_fit(model, model * [1.0, 1.0, -1.0])
    assert np.linalg.det(R) == pytest.approx(1.0)


def test_any_two_layouts_give_the_pose_and_their_fit() -> None:
    """Four platform nests and five base monuments, not the robot file's spheres: the same pose, batched too; a nest
    moved 0.3 mm shows in the platform registration's RMS alone."""
    rng = np.random.default_rng(7)
    nests = np.array([[900.0, 0.0, 60.0], [0.0, 900.0, 60.0], [-900.0, 0.0, 60.0], [0.0, -900.0, 80.0]])
    monuments = np.array([[3000.0, 0.0, 0.0], [0.0, 3000.0, 50.0], [-3000.0, 0.0, 0.0], [0.0, -3000.0, 20.0],
                          [1500.0, 1500.0, 400.0]])
    poses = np.array([random_pose(rng) for _ in range(4)])
    platform, base = [], []
    for pose in poses:
        rot, t = random_cmm(rng)
        R = rotation_matrix(np.radians(pose[3:]))
        platform.append((nests @ R.T + pose[:3]) @ rot.T + t)
        base.append(monuments @ rot.T + t)
    fit = pose_from_points(np.array(platform), nests, np.array(base), monuments)
    np.testing.assert_allclose(fit.pose, poses, atol=1e-8)
    assert fit.rms_residual_mm.shape == (4, 2) and np.all(fit.rms_residual_mm < 1e-9)
    moved = np.array(platform[0])
    moved[2, 0] += 0.3
    one = pose_from_points(moved, nests, base[0], monuments)
    assert one.platform_rms_mm > 0.1 and one.base_rms_mm < 1e-9
    with pytest.raises(ValueError, match="at least 3 points"):
        pose_from_points(platform[0][:2], nests[:2], base[0], monuments)
    with pytest.raises(ValueError, match=r"\(5, 3\) or \(N, 5, 3\)"):
        pose_from_points(platform[0], nests, base[0][:4], monuments)


def test_shape_and_value_errors() -> None:
    good = np.zeros((3, 3))
    with pytest.raises(ValueError, match=r"\(3, 3\) or \(N, 3, 3\)"):
        pose_from_spheres(np.zeros((4, 3)), good, ROBOT)
    with pytest.raises(ValueError, match="batches of the same length"):
        pose_from_spheres(np.zeros((2, 3, 3)), good, ROBOT)
    bad = ROBOT.base_spheres.copy()
    bad[0, 0] = np.nan
    with pytest.raises(ValueError, match="NaN"):
        pose_from_spheres(ROBOT.platform_spheres, bad, ROBOT)


def test_recovers_the_simulated_rigs_true_pose() -> None:
    from sim_devices.rig.config import RigConfig, load_errors
    from sim_devices.rig.rig import SimulatedRig

    rig = SimulatedRig(ROBOT, RigConfig(seed=5, errors=load_errors("table5"), cmm_noise_mm=0.0))
    for pose in [random_pose(np.random.default_rng(k)) * [0.5, 0.5, 1, 0.1, 0.1, 0.05] for k in range(5)]:
        rig.move_to_lengths(rig.controller_ik(pose))
        fit = pose_from_spheres(*rig.measure_spheres(), ROBOT)
        np.testing.assert_allclose(fit.pose, rig.true_pose(), atol=1e-8)
