"""Pose ordering: valid permutations, home to home, never slower than the design order, seeded, and the
drift-confounding bound held."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from hilcal.kinematics import Geometry
from hilcal.planning.machine_time import MotionRules, MotionTiming, calibration_phases, estimate_route
from hilcal.planning.ordering import drift_confounding, order_route
from hilcal.robot import load_robot
from tests.poses import feasible_random_poses

SMALL_ROBOT = Path(__file__).resolve().parents[3] / "examples" / "hexapod_small.toml"
TIMING = MotionTiming(leg_speed_mm_s=50.0, leg_accel_mm_s2=100.0, settle_s=2.0, cmm_s_per_pose=30.0,
                      move_overhead_s=0.25)


@pytest.fixture(scope="module")
def poses(robot):
    rng = np.random.default_rng(7)
    return feasible_random_poses(robot, 20, rng), feasible_random_poses(robot, 10, rng)


def test_valid_permutations_home_to_home_and_faster(robot, poses):
    measure, verify = poses
    geom = Geometry.nominal(robot)
    out = order_route(geom, robot.home, measure, verify, MotionRules(), TIMING, seed=3)
    assert sorted(out.measure_order.tolist()) == list(range(20))
    assert sorted(out.verify_order.tolist()) == list(range(10))
    design = estimate_route(geom, robot.home, calibration_phases(measure, verify), MotionRules(), TIMING, robot.home)
    ordered = estimate_route(geom, robot.home, calibration_phases(measure[out.measure_order],
                                                                  verify[out.verify_order]),
                             MotionRules(), TIMING, robot.home)
    # the optimiser's objective is the whole route from home back to home, as estimated
    assert out.motion_s == pytest.approx(ordered.motion_s)
    assert out.design_motion_s == pytest.approx(design.motion_s)
    # random poses in random order: a good route is far shorter
    assert out.motion_s < 0.75 * design.motion_s
    assert out.confounding.absorbed_fraction <= out.confounding_bound + 1e-9


def test_seeded_and_deterministic(robot, poses):
    measure, verify = poses
    geom = Geometry.nominal(robot)
    a = order_route(geom, robot.home, measure, verify, MotionRules(), TIMING, seed=11)
    b = order_route(geom, robot.home, measure, verify, MotionRules(), TIMING, seed=11)
    np.testing.assert_array_equal(a.measure_order, b.measure_order)
    np.testing.assert_array_equal(a.verify_order, b.verify_order)
    assert a.motion_s == b.motion_s and a.seed == 11


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_never_worse_than_the_design_order_on_a_small_hexapod(seed):
    robot = load_robot(SMALL_ROBOT)
    rng = np.random.default_rng(seed)
    measure = feasible_random_poses(robot, 12, rng)
    # a design order that is already short: sorted along a sweep of x
    measure = measure[np.argsort(measure[:, 0])]
    verify = feasible_random_poses(robot, 4, rng)
    fast = MotionTiming(leg_speed_mm_s=20.0, leg_accel_mm_s2=200.0, settle_s=0.2, cmm_s_per_pose=10.0)
    out = order_route(Geometry.nominal(robot), robot.home, measure, verify, MotionRules(), fast, seed=seed)
    assert out.motion_s <= out.design_motion_s + 1e-9


def test_repeats_cost_time_but_not_order(robot, poses):
    measure, verify = poses
    geom = Geometry.nominal(robot)
    counts = np.ones(20, dtype=int)
    counts[4] = 4
    out = order_route(geom, robot.home, measure, verify, MotionRules(), TIMING, measure_counts=counts)
    rows = np.repeat(measure[out.measure_order], counts[out.measure_order], axis=0)
    est = estimate_route(geom, robot.home, calibration_phases(rows, verify[out.verify_order]), MotionRules(),
                         TIMING, robot.home)
    assert out.motion_s == pytest.approx(est.motion_s)
    assert est.phase("measure").n_poses == 23


def test_drift_confounding_sees_a_drift_that_follows_the_workspace(robot, rng):
    geom = Geometry.nominal(robot)
    q = feasible_random_poses(robot, 32, rng)
    aligned = drift_confounding(geom, q, q[:, 3])  # time follows roll
    assert aligned.absorbed_fraction > 0.6
    assert aligned.max_abs_corr_pose == pytest.approx(1.0)
    random = [drift_confounding(geom, q, rng.permutation(32)).absorbed_fraction for _ in range(30)]
    assert np.median(random) < 0.35
    # a pose measured three times at (about) the same time counts as three rows
    rows, times = np.insert(q, 5, [q[5], q[5]], axis=0), np.insert(q[:, 3], 5, [q[5, 3], q[5, 3]])
    counts = np.ones(32, dtype=int)
    counts[5] = 3
    assert drift_confounding(geom, q, q[:, 3], counts).absorbed_fraction == pytest.approx(
        drift_confounding(geom, rows, times).absorbed_fraction)
    # invariant to the time origin and unit
    scaled = drift_confounding(geom, q, 60.0 * q[:, 3] + 1000.0)
    assert scaled.absorbed_fraction == pytest.approx(aligned.absorbed_fraction)


def test_bound_is_held_against_a_shorter_but_confounded_route(robot, poses):
    measure, verify = poses
    geom = Geometry.nominal(robot)
    free = order_route(geom, robot.home, measure, verify, MotionRules(), TIMING, confounding_bound=1.0)
    tight = order_route(geom, robot.home, measure, verify, MotionRules(), TIMING,
                        confounding_bound=0.5 * free.confounding.absorbed_fraction)
    assert tight.confounding.absorbed_fraction <= tight.confounding_bound + 1e-9
    assert tight.motion_s >= free.motion_s - 1e-6
