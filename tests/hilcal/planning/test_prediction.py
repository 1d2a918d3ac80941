"""The verify-error prediction of a sequential plan (hilcal.planning.prediction) against repeated noisy calibrations,
and the noise found in repeated poses."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from hilcal.identification import identify
from hilcal.kinematics import Geometry, forward_kinematics, inverse_kinematics
from hilcal.planning.design import pose_jacobians
from hilcal.planning.prediction import (
    Draws,
    PoseNoise,
    parameter_covariance_parts,
    predict_verify_max,
    repeat_groups,
    repeat_noise,
)
from tests.poses import feasible_random_poses


def _noisy(poses: np.ndarray, sigma_p: float, sigma_r_mm: float, length_mm: float, rng: np.random.Generator
           ) -> np.ndarray:
    """Poses with N(0, sigma_p) on x, y, z and a rotation vector N(0, sigma_r / length) rad in the base frame."""
    out = poses.copy()
    out[:, :3] += rng.normal(0.0, sigma_p, (len(poses), 3))
    R = Rotation.from_euler("ZYX", poses[:, [5, 4, 3]], degrees=True)
    dR = Rotation.from_rotvec(rng.normal(0.0, sigma_r_mm / length_mm, (len(poses), 3)))
    out[:, [5, 4, 3]] = (dR * R).as_euler("ZYX", degrees=True)
    return out


def test_repeat_noise_recovers_the_sigmas_of_many_repeats(robot, rng):
    poses = feasible_random_poses(robot, 5, rng)
    commanded = np.repeat(poses, 200, axis=0)
    measured = _noisy(commanded, 0.004, 0.009, robot.characteristic_length_mm, rng)
    noise = repeat_noise(commanded, measured, robot.characteristic_length_mm)
    assert noise.position_mm == pytest.approx(0.004, rel=0.05)
    assert noise.rotation_mm == pytest.approx(0.009, rel=0.05)
    assert noise.dof == (3 * 5 * 199,) * 6 and noise.shared
    assert len(repeat_groups(commanded)) == 5


def test_no_repeat_means_no_noise_and_groups_keep_the_visit_order(robot, rng):
    poses = feasible_random_poses(robot, 4, rng)
    assert repeat_noise(poses, poses, robot.characteristic_length_mm) is None
    rows = np.vstack([poses[2], poses[0], poses[2], poses[1], poses[0], poses[0]])
    assert [g.tolist() for g in repeat_groups(rows)] == [[0, 2], [1, 4, 5]]


def _max_verify_errors(robot, rng, measure, verify, sigma, n_runs):
    """Maximum position error over the verify poses after calibrating on noisy measure poses, n_runs times."""
    true = Geometry.nominal(robot).perturbed(rng.normal(0.0, 0.5, 42))
    legs = inverse_kinematics(Geometry.nominal(robot), measure)
    legs_v = inverse_kinematics(Geometry.nominal(robot), verify)
    reached = forward_kinematics(true, legs, measure)
    reached_v = forward_kinematics(true, legs_v, verify)
    out = []
    for _ in range(n_runs):
        fit = identify(robot, legs, _noisy(reached, sigma, sigma, robot.characteristic_length_mm, rng),
                       method="one_step")
        predicted = forward_kinematics(fit.geometry(robot), legs_v, verify)
        shown = reached_v[:, :3] + rng.normal(0.0, sigma, (len(verify), 3))
        out.append(np.linalg.norm(shown - predicted[:, :3], axis=1).max())
    return np.array(out)


def test_prediction_matches_repeated_calibrations(robot):
    rng = np.random.default_rng(7)
    measure, verify = feasible_random_poses(robot, 14, rng), feasible_random_poses(robot, 10, rng)
    sigma = 0.01
    empirical = _max_verify_errors(robot, rng, measure, verify, sigma, 200)
    known = PoseNoise.isotropic(sigma, sigma, 1e9, 1e9, "stated")
    pred = predict_verify_max(pose_jacobians(robot, measure), pose_jacobians(robot, verify)[:, :3], known,
                              Draws.seeded(0, len(verify), 20000))
    assert pred.max_mm == pytest.approx(np.median(empirical), rel=0.08)
    assert pred.upper_mm == pytest.approx(np.quantile(empirical, 0.95), rel=0.12)
    assert pred.low_mm == pytest.approx(np.quantile(empirical, 0.05), rel=0.12)
    assert pred.floor_upper_mm < pred.upper_mm


def test_an_uncertain_noise_level_widens_the_bound_and_the_bound_scales_with_the_noise(robot, rng):
    measure, verify = feasible_random_poses(robot, 12, rng), feasible_random_poses(robot, 8, rng)
    J, Jv = pose_jacobians(robot, measure), pose_jacobians(robot, verify)[:, :3]
    draws = Draws.seeded(1, len(verify), 5000)
    sure = predict_verify_max(J, Jv, PoseNoise.isotropic(0.005, 0.005, 1e9, 1e9, "stated"), draws)
    few = predict_verify_max(J, Jv, PoseNoise.isotropic(0.005, 0.005, 9, 9, "4 repeats"), draws)
    double = predict_verify_max(J, Jv, PoseNoise.isotropic(0.010, 0.010, 1e9, 1e9, "stated"), draws)
    assert few.upper_mm > 1.2 * sure.upper_mm
    assert double.upper_mm == pytest.approx(2 * sure.upper_mm, rel=1e-9)
    assert double.parameter_rms_mm == pytest.approx(2 * sure.parameter_rms_mm, rel=1e-9)


def test_draws_shared_across_noise_estimates_predict_as_fresh_draws(robot, rng):
    """A run predicts many designs under each noise estimate with one set of draws, which keeps the draws scaled by the
    last estimates: every estimate, in any order, must predict exactly what fresh draws of the same seed predict."""
    measure, verify = feasible_random_poses(robot, 12, rng), feasible_random_poses(robot, 6, rng)
    J, Jv = pose_jacobians(robot, measure), pose_jacobians(robot, verify)[:, :3]
    a = PoseNoise.isotropic(0.005, 0.004, 9, 9, "4 repeats")
    noises = [a, PoseNoise(a.sigma_mm, a.dof, False, "per component"),
              PoseNoise.isotropic(0.006, 0.004, 9, 9, "4 repeats"), PoseNoise.isotropic(0.005, 0.004, 15, 9, "6"),
              PoseNoise((0.005, 0.004, 0.003, 0.004, 0.004, 0.004), (9, 8, 7, 9, 9, 9), False, "per component"),
              PoseNoise.isotropic(0.005, 0.007, 9, 9, "4 repeats"), a]
    shared = Draws.seeded(2, len(verify), 2000)
    for noise in noises:
        fresh = predict_verify_max(J, Jv, noise, Draws.seeded(2, len(verify), 2000))
        again = predict_verify_max(J, Jv, noise, shared)
        assert (again.max_mm, again.low_mm, again.upper_mm, again.floor_upper_mm) == (
            fresh.max_mm, fresh.low_mm, fresh.upper_mm, fresh.floor_upper_mm)


def test_covariance_parts_add_up_to_the_least_squares_covariance(robot, rng):
    J = pose_jacobians(robot, feasible_random_poses(robot, 10, rng))
    parts = parameter_covariance_parts(J)
    A = J.reshape(-1, 42)
    np.testing.assert_allclose(parts.sum(axis=0), np.linalg.inv(A.T @ A), rtol=1e-6, atol=1e-12)
    with pytest.raises(np.linalg.LinAlgError):
        parameter_covariance_parts(J[:6])


def test_pose_noise_refuses_nonsense():
    with pytest.raises(ValueError, match="positive"):
        PoseNoise.isotropic(0.0, 0.01, 9, 9, "x")
    with pytest.raises(ValueError, match="6 positive"):
        PoseNoise((0.01,) * 5, (9.0,) * 5, False, "x")


def test_a_models_misfit_widens_the_bound_by_its_covariance(robot, rng):
    """The misfit's part of the parameters' covariance (hilcal.misfit) is drawn on top of the noise's: the predicted
    maximum is the one of a Monte Carlo written here with both parts, and the prediction says the model is
    incomplete."""
    measure, verify = feasible_random_poses(robot, 14, rng), feasible_random_poses(robot, 10, rng)
    J, Jv = pose_jacobians(robot, measure), pose_jacobians(robot, verify)[:, :3]
    sigma = 0.005
    misfit = np.zeros((42, 42))
    dl0 = [7 * i + 6 for i in range(6)]
    misfit[np.ix_(dl0, dl0)] = 0.02**2 * (0.5 * np.eye(6) + 0.5)  # leg offsets off by 20 µm, half of it shared
    pred = predict_verify_max(J, Jv, PoseNoise.isotropic(sigma, sigma, 1e9, 1e9, "stated"),
                              Draws.seeded(3, len(verify), 20000), misfit_covariance=misfit)
    A = J.reshape(-1, 42)
    cov = sigma**2 * np.linalg.inv(A.T @ A) + misfit
    w, V = np.linalg.eigh(cov)
    dp = (V * np.sqrt(np.clip(w, 0, None))) @ rng.standard_normal((42, 20000))
    errors = np.einsum("vij,jd->vid", Jv, dp) + rng.normal(0.0, sigma, (len(verify), 3, 20000))
    worst = np.linalg.norm(errors, axis=1).max(axis=0)
    assert pred.max_mm == pytest.approx(np.median(worst), rel=0.03)
    assert pred.upper_mm == pytest.approx(np.quantile(worst, 0.95), rel=0.03)
    assert pred.to_json()["model_incomplete"] is True
    plain = predict_verify_max(J, Jv, PoseNoise.isotropic(sigma, sigma, 1e9, 1e9, "stated"),
                               Draws.seeded(3, len(verify), 20000))
    assert plain.upper_mm < 0.8 * pred.upper_mm and plain.to_json()["model_incomplete"] is False
