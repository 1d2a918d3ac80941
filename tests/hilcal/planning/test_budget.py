"""Time-budgeted designs: the predicted verification error against repeated noisy identifications, and the
choice of the largest nested design that fits the budget."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from hilcal.identification import identify
from hilcal.kinematics import Geometry, forward_kinematics, inverse_kinematics
from hilcal.metrics import pose_errors
from hilcal.planning.budget import BudgetError, budgeted_design, elimination_order, predicted_verify_error
from hilcal.planning.machine_time import MotionRules, MotionTiming
from tests.poses import feasible_random_poses

TIMING = MotionTiming(leg_speed_mm_s=50.0, leg_accel_mm_s2=100.0, settle_s=2.0, cmm_s_per_pose=30.0,
                      move_overhead_s=0.25)


def _noisy(poses: np.ndarray, sigma_mm: float, length_mm: float, rng: np.random.Generator) -> np.ndarray:
    """Poses with N(0, sigma) on x, y, z and a rotation vector N(0, sigma / length) rad applied in the base frame."""
    out = poses.copy()
    out[:, :3] += rng.normal(0.0, sigma_mm, (len(poses), 3))
    R = Rotation.from_euler("ZYX", poses[:, [5, 4, 3]], degrees=True)
    dR = Rotation.from_rotvec(rng.normal(0.0, sigma_mm / length_mm, (len(poses), 3)))
    out[:, [5, 4, 3]] = (dR * R).as_euler("ZYX", degrees=True)
    return out


def test_predicted_verify_error_matches_repeated_identifications(robot):
    rng = np.random.default_rng(3)
    measure, verify = feasible_random_poses(robot, 20, rng), feasible_random_poses(robot, 8, rng)
    sigma = 0.01
    true = Geometry.nominal(robot).perturbed(rng.normal(0.0, 0.5, 42))
    legs, legs_v = inverse_kinematics(true, measure), inverse_kinematics(true, verify)
    errors = []
    for _ in range(24):  # the one-step (linearized) LS fit keeps this fast; the iterated fit agrees as well
        fit = identify(robot, legs, _noisy(measure, sigma, robot.characteristic_length_mm, rng), method="one_step")
        predicted = forward_kinematics(fit.geometry(robot), legs_v, verify)
        errors.append(pose_errors(predicted, verify)[0])
    empirical_rms = float(np.sqrt(np.mean(np.square(errors))))
    pred = predicted_verify_error(robot, measure, verify, sigma)
    assert pred.rms_position_mm == pytest.approx(empirical_rms, rel=0.25)
    assert pred.max_position_mm >= pred.rms_position_mm
    # twice the noise, twice the error; more poses, less error
    assert predicted_verify_error(robot, measure, verify, 2 * sigma).rms_position_mm == pytest.approx(
        2 * pred.rms_position_mm)
    assert predicted_verify_error(robot, measure[:12], verify, sigma).rms_position_mm > pred.rms_position_mm


def test_elimination_drops_the_least_informative_first_and_keeps_the_repeat(robot, rng):
    poses = feasible_random_poses(robot, 14, rng)
    order = elimination_order(robot, poses, keep=5)
    assert sorted(order.tolist()) == list(range(14)) and order[-1] == 5
    # dropping the first-ranked pose loses less information than dropping any other one
    from hilcal.planning.design import information_matrix
    full = information_matrix(robot, poses)
    losses = [np.linalg.slogdet(full - information_matrix(robot, poses[k:k + 1]))[1] for k in range(14)]
    assert order[0] == int(np.argmax(losses))


@pytest.fixture(scope="module")
def small_design(robot):
    rng = np.random.default_rng(5)
    return feasible_random_poses(robot, 16, rng), feasible_random_poses(robot, 4, rng)


def test_budget_picks_the_largest_design_that_fits(robot, small_design):
    measure, verify = small_design
    rules = MotionRules()
    kw = {"repeat": 0, "repeats": 3, "min_measure": 10}
    roomy = budgeted_design(robot, measure, verify, 1e6, rules, TIMING, **kw)
    assert roomy.chosen.n_measure == 16 and roomy.chosen.d_efficiency == pytest.approx(1.0)
    assert len(roomy.options) == 1
    full_s = roomy.chosen.estimate.total_s
    smallest = budgeted_design(robot, measure, verify, full_s - 1e-6, rules, TIMING, **kw).options[-1]
    assert smallest.n_measure == 10
    budget = 0.5 * (full_s + smallest.estimate.total_s)
    out = budgeted_design(robot, measure, verify, budget, rules, TIMING, **kw)
    assert out.chosen.estimate.total_s <= budget
    assert 10 <= out.chosen.n_measure < 16
    assert 0 in out.chosen.measure_index
    assert out.chosen.estimate.phase("measure").n_poses == out.chosen.n_measure + 3
    assert smallest.d_efficiency < out.chosen.d_efficiency < 1.0
    assert smallest.predicted.rms_position_mm > out.chosen.predicted.rms_position_mm > \
        roomy.chosen.predicted.rms_position_mm
    # the choice is the largest that fits: one pose more does not
    with pytest.raises(BudgetError):
        budgeted_design(robot, measure, verify, budget, rules, TIMING, **{**kw,
                                                                          "min_measure": out.chosen.n_measure + 1})
    with pytest.raises(BudgetError, match="over the budget"):
        budgeted_design(robot, measure, verify, 0.9 * smallest.estimate.total_s, rules, TIMING, **kw)
