"""Identification against the independent simulated rig: exact recovery without noise, honest statistics."""

from __future__ import annotations

import numpy as np
import pytest

from hilcal.identifiability import identifiability
from hilcal.identification import IdentificationError, identify
from hilcal.kinematics import Geometry, forward_kinematics, inverse_kinematics
from sim_devices.rig.config import GeometryErrors, RigConfig, load_errors
from sim_devices.rig.rig import SimulatedRig
from tests.poses import feasible_random_poses


def _rig_data(robot, errors: GeometryErrors, poses: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Reported legs and exact true poses from the independent rig (no CMM noise, no quantization)."""
    rig = SimulatedRig(robot, RigConfig(errors=errors, cmm_noise_mm=0.0, leg_resolution_mm=0.0))
    legs = rig.controller_ik(poses)
    return legs, rig.true_poses_for_lengths(legs)


@pytest.fixture(scope="module")
def table2_data(robot):
    poses = feasible_random_poses(robot, 32, np.random.default_rng(7))
    errors = load_errors("table2", robot)
    return errors.to_vector(), *_rig_data(robot, errors, poses)


@pytest.mark.parametrize("estimator", ["ls", "linf"])
@pytest.mark.parametrize("formulation", ["forward", "implicit"])
def test_iterated_fit_recovers_table2_errors_without_noise(robot, table2_data, estimator, formulation):
    truth, legs, poses = table2_data
    result = identify(robot, legs, poses, estimator=estimator, formulation=formulation)
    assert result.converged
    np.testing.assert_allclose(result.x, truth, atol=1e-5)
    assert result.max_abs_residual < 1e-7


def test_one_step_is_close_but_not_exact(robot, table2_data):
    truth, legs, poses = table2_data
    one = identify(robot, legs, poses, method="one_step")
    err = np.abs(one.x - truth).max()
    assert 1e-7 < err < 0.1, "linearizing at the nominal geometry leaves a small second-order error"


def test_linf_minimises_the_maximum_and_ls_the_sum_of_squares(robot, table2_data):
    _, legs, poses = table2_data
    noisy = poses + np.random.default_rng(3).standard_t(3, size=poses.shape) * [0.01, 0.01, 0.01, 1e-4, 1e-4, 1e-4]
    ls = identify(robot, legs, noisy, estimator="ls")
    linf = identify(robot, legs, noisy, estimator="linf")
    assert linf.max_abs_residual <= ls.max_abs_residual + 1e-9
    assert ls.rms_residual <= linf.rms_residual + 1e-9


def test_standard_errors_match_monte_carlo_scatter(robot):
    """sigma^2 uses m - p degrees of freedom; the predicted scatter must match repeated noisy fits."""
    rng = np.random.default_rng(11)
    nominal = Geometry.nominal(robot)
    poses = feasible_random_poses(robot, 40, rng)
    truth = rng.normal(0.0, 0.5, 42)
    legs = inverse_kinematics(nominal, poses)
    true_poses = forward_kinematics(nominal.perturbed(truth), legs, poses)
    sigma = 0.01
    estimates, predicted, sigmas = [], [], []
    for _ in range(40):
        noisy = true_poses.copy()
        noisy[:, :3] += rng.normal(0.0, sigma, (40, 3))
        noisy[:, 3:] += np.degrees(rng.normal(0.0, sigma / robot.characteristic_length_mm, (40, 3)))
        res = identify(robot, legs, noisy, estimator="ls", formulation="forward")
        estimates.append(res.x)
        predicted.append(res.std_errors)
        sigmas.append(res.sigma)
    assert np.mean(sigmas) == pytest.approx(sigma, rel=0.1)
    ratio = np.std(estimates, axis=0, ddof=1) / np.mean(predicted, axis=0)
    assert 0.75 < np.median(ratio) < 1.3


def test_too_few_poses_is_a_clear_error(robot, table2_data):
    _, legs, poses = table2_data
    with pytest.raises(IdentificationError, match="need at least 8 poses"):
        identify(robot, legs[:7], poses[:7])


def test_paper60_model_is_rank_deficient_but_fits(robot, table2_data):
    _, legs, poses = table2_data
    rep = identifiability(robot, poses, "60")
    assert rep.rank < 60
    res = identify(robot, legs, poses, model="60", method="one_step")
    assert res.rank == rep.rank
    with pytest.raises(IdentificationError, match="linear"):
        identify(robot, legs, poses, model="60", method="iterated")


def test_42_model_identifiable_and_weak_modes_explained(robot):
    poses = feasible_random_poses(robot, 32, np.random.default_rng(5))
    rep = identifiability(robot, poses, "42")
    assert rep.rank == 42
    assert any("sliding a joint along the leg axis" in text and "base joint b" in text for text in rep.weak_explained)
