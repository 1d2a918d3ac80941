"""The uncertainty of the certificate's figures: each Monte Carlo result against a value worked out independently
(a linearized propagation, a closed form, or a simulation of the same experiment repeated)."""

from __future__ import annotations

import numpy as np
import pytest

from hilcal.acceptance.uncertainty import (
    accuracy_figures,
    ap_figures,
    cmm_pose_covariance,
    model_uncertainty,
    pooled_covariance,
    repeated_groups,
    rp_figures,
    rp_statistics,
)
from hilcal.error_models import forward_jacobian
from hilcal.kinematics import Geometry, split_pose
from hilcal.pose_measurement import pose_from_spheres
from hilcal.robot import Robot


def test_cmm_covariance_matches_the_linearized_propagation(robot: Robot) -> None:
    """GUM's law of propagation (J u² Jᵀ, J by central differences) against the Monte Carlo covariance."""
    u = 0.002
    R, t = split_pose(robot.home)
    platform = robot.platform_spheres @ R.T + t
    x0 = np.concatenate([platform.ravel(), robot.base_spheres.ravel()])
    n_p = platform.size

    def pose(x: np.ndarray) -> np.ndarray:
        return pose_from_spheres(x[:n_p].reshape(-1, 3), x[n_p:].reshape(-1, 3), robot).pose

    h = 1e-4
    J = np.column_stack([(pose(x0 + h * e) - pose(x0 - h * e)) / (2 * h) for e in np.eye(len(x0))])
    linear = u**2 * J @ J.T
    mc = cmm_pose_covariance(robot, u, draws=20000, seed=1)
    np.testing.assert_allclose(np.sqrt(np.diag(mc)), np.sqrt(np.diag(linear)), rtol=0.03)
    doubled = cmm_pose_covariance(robot, 2 * u, draws=20000, seed=1)
    np.testing.assert_allclose(np.diag(doubled), 4 * np.diag(mc), rtol=1e-3)  # same draws, twice as large


def test_accuracy_figures_of_one_far_pose_have_the_noise_along_the_error() -> None:
    """|e + d| with |e| >> sigma varies by the component of d along e: its standard deviation is sigma."""
    sigma = 0.01
    measured = np.array([[3.0, 4.0, 1000.0, 0.5, 0.0, 0.0]])
    commanded = np.array([[0.0, 0.0, 1000.0, 0.0, 0.0, 0.0]])
    cov = np.diag([sigma**2] * 3 + [1e-6] * 3)
    f = accuracy_figures(measured, commanded, cov, draws=20000, seed=2)
    assert f["max_position_mm"].value == pytest.approx(5.0)
    assert f["max_position_mm"].u == pytest.approx(sigma, rel=0.03)
    assert f["max_position_mm"].expanded == pytest.approx(2 * sigma, rel=0.03)
    assert f["max_orientation_deg"].value == pytest.approx(0.5)
    assert f["max_orientation_deg"].u == pytest.approx(1e-3, rel=0.03)
    assert accuracy_figures(measured, commanded, None)["rms_position_mm"].u == 0.0


def test_ap_uncertainty_combines_the_scatter_of_the_mean_and_the_cmm() -> None:
    """AP_P far along x: u² = S_x² / n + u_cmm,x² (the barycentre's x variance), worked out from the data."""
    rng = np.random.default_rng(3)
    n = 30
    attained = np.zeros((n, 6))
    attained[:, 0] = 2.0 + rng.normal(0.0, 0.05, n)
    cmm = np.diag([0.01**2, 0.01**2, 0.01**2, 1e-8, 1e-8, 1e-8])
    f = ap_figures(attained, np.zeros(6), cmm, draws=20000, seed=4)
    expected_u = np.sqrt(np.var(attained[:, 0], ddof=1) / n + 0.01**2)
    assert f["ap_p_mm"].value == pytest.approx(abs(attained[:, 0].mean()))
    assert f["ap_p_mm"].u == pytest.approx(expected_u, rel=0.05)
    assert f["ap_a_deg"].u == pytest.approx(1e-4, rel=0.05)


def test_rp_bootstrap_matches_the_spread_of_repeated_experiments() -> None:
    """The bootstrap u of RP from one experiment of 30 cycles against the standard deviation of RP over 2000
    independent experiments of the same machine (isotropic scatter 0.02 mm per axis)."""
    rng = np.random.default_rng(5)
    sigma, n = 0.02, 30
    experiments = rng.normal(0.0, sigma, (2000, n, 6))
    true_spread = np.std(rp_statistics(experiments)[:, 0], ddof=1)
    estimates = [rp_figures(experiments[k], draws=1000, seed=k)["rp_l_mm"].u for k in range(20)]
    assert np.median(estimates) == pytest.approx(true_spread, rel=0.3)
    # RP_l of an isotropic normal scatter: l̄ ~ 1.596 sigma and S_l ~ 0.673 sigma (Maxwell), so RP ~ 3.62 sigma.
    assert np.mean(rp_statistics(experiments)[:, 0]) == pytest.approx(3.62 * sigma, rel=0.03)


def test_pooled_covariance_by_hand() -> None:
    # Group 1: x = 0, 2 (mean 1, squares 1 + 1 = 2); group 2: x = 1, 1, 4 (mean 2, squares 1 + 1 + 4 = 6).
    # Pooled variance of x = (2 + 6) / ((2 - 1) + (3 - 1)) = 8 / 3 with 3 degrees of freedom.
    g1 = np.zeros((2, 6))
    g1[:, 0] = [0.0, 2.0]
    g2 = np.zeros((3, 6))
    g2[:, 0] = [1.0, 1.0, 4.0]
    cov, dof = pooled_covariance([g1, g2, np.zeros((1, 6))])
    assert dof == 3
    assert cov[0, 0] == pytest.approx(8.0 / 3.0)
    assert np.count_nonzero(cov) == 1
    assert pooled_covariance([]) == (None, 0)


def test_repeated_groups_by_commanded_pose() -> None:
    cmd = np.array([[0.0] * 6, [1.0] * 6, [0.0] * 6, [2.0] * 6, [0.0] * 6])
    meas = cmd + np.arange(5)[:, None]
    groups = repeated_groups(cmd, meas)
    assert len(groups) == 1
    np.testing.assert_array_equal(groups[0][:, 0], [0.0, 2.0, 4.0])


def test_model_uncertainty_scales_with_the_covariance(robot: Robot) -> None:
    poses = np.array([robot.home, robot.home + np.array([100.0, 0, 0, 2.0, 0, 0])])
    rng = np.random.default_rng(6)
    A = rng.normal(size=(42, 42))
    C = 1e-6 * A @ A.T
    one = model_uncertainty(robot, C, poses)
    four = model_uncertainty(robot, 4 * C, poses)
    assert four.rms_position_mm == pytest.approx(2 * one.rms_position_mm)
    assert one.max_position_mm >= one.rms_position_mm > 0
    assert model_uncertainty(robot, np.zeros((42, 42)), poses).max_position_mm == 0.0
    # Only an error of leg 1's offset dl0 (the 7th parameter): at home its pose error is J[:, 6] times its sigma.
    C1 = np.zeros((42, 42))
    C1[6, 6] = 0.01**2
    J = forward_jacobian(Geometry.nominal(robot), robot.home[None], robot.characteristic_length_mm)[0]
    assert model_uncertainty(robot, C1, robot.home[None]).max_position_mm == pytest.approx(
        0.01 * np.linalg.norm(J[:3, 6]))
