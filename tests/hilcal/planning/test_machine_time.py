"""The motion-time model against hand-computed trapezoid cases, and the batched move costs against the
step-by-step setpoints the procedure executes."""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest

from hilcal.kinematics import Geometry, inverse_kinematics
from hilcal.planning.machine_time import (
    MotionRules,
    MotionTiming,
    calibration_phases,
    estimate_route,
    format_minutes,
    move_costs,
    move_time,
    repeatable_pose,
    trapezoid_time,
    visit_setpoints,
)
from tests.poses import feasible_random_poses

TIMING = MotionTiming(leg_speed_mm_s=50.0, leg_accel_mm_s2=100.0, settle_s=2.0, cmm_s_per_pose=30.0,
                      move_overhead_s=0.25)


def test_trapezoid_hand_cases():
    # 100 mm at 50 mm/s, 100 mm/s²: 0.5 s (12.5 mm) up, 75 mm cruising (1.5 s), 0.5 s down.
    assert trapezoid_time(100.0, 50.0, 100.0) == pytest.approx(2.5)
    # 16 mm: never reaches 50 mm/s; 8 mm up in sqrt(2*8/100) = 0.4 s, 8 mm down.
    assert trapezoid_time(16.0, 50.0, 100.0) == pytest.approx(0.8)
    # 25 mm = v²/a: the triangle just touches the cruise speed; both formulas give 1 s.
    assert trapezoid_time(25.0, 50.0, 100.0) == pytest.approx(1.0)
    assert trapezoid_time(np.nextafter(25.0, 0), 50.0, 100.0) == pytest.approx(1.0)
    assert trapezoid_time(-100.0, 50.0, 100.0) == pytest.approx(2.5)
    assert trapezoid_time(0.0, 50.0, 100.0) == 0.0
    # very large acceleration: distance / speed
    assert trapezoid_time(300.0, 50.0, 1e12) == pytest.approx(6.0)


def test_move_time_is_the_slowest_leg_plus_overhead():
    legs_from = np.full(6, 4300.0)
    legs_to = legs_from + np.array([16.0, -100.0, 0.0, 5.0, -25.0, 3.0])
    assert move_time(legs_from, legs_to, TIMING) == pytest.approx(2.5 + 0.25)


def test_timing_and_rules_are_validated():
    with pytest.raises(ValueError):
        MotionTiming(0.0, 100.0, 1.0, 1.0)
    with pytest.raises(ValueError):
        MotionTiming(50.0, 100.0, -1.0, 1.0)
    with pytest.raises(ValueError):
        MotionRules(max_step_mm=50.0, approach_mm=5.0, retreat_mm=2.0)


def test_visit_setpoints_follow_the_motion_rules(robot, rng):
    geom = Geometry.nominal(robot)
    rules = MotionRules(max_step_mm=50.0, approach_mm=2.0, retreat_mm=10.0)
    start, target = feasible_random_poses(robot, 2, rng)
    steps = visit_setpoints(geom, start, target, rules)
    kinds = [k for k, _ in steps]
    assert kinds[-2:] == ["approach", "target"] and set(kinds[:-2]) <= {"transit"}
    legs = np.array([inverse_kinematics(geom, start), *[lg for _, lg in steps]])
    assert np.max(np.abs(np.diff(legs[:-2], axis=0))) <= 50.0 + 1e-9
    target_legs = inverse_kinematics(geom, target)
    np.testing.assert_allclose(steps[-2][1], target_legs - 2.0)
    np.testing.assert_allclose(steps[-1][1], target_legs)
    repeat = visit_setpoints(geom, target, target, rules)
    assert [k for k, _ in repeat] == ["retreat", "approach", "target"]
    np.testing.assert_allclose(repeat[0][1], target_legs - 10.0)
    home = visit_setpoints(geom, target, robot.home, rules, approach=False)
    assert home[-1][0] == "target" and all(k == "transit" for k, _ in home[:-1])


def test_batched_costs_equal_the_setpoint_sequence(robot, rng):
    geom = Geometry.nominal(robot)
    rules = MotionRules()
    poses = feasible_random_poses(robot, 12, rng)
    starts, targets = poses[:6], poses[6:]
    starts[2] = targets[2]  # one repeat
    costs = move_costs(geom, starts, targets, rules, TIMING)
    for k in range(6):
        steps = visit_setpoints(geom, starts[k], targets[k], rules)
        legs = np.array([inverse_kinematics(geom, starts[k]), *[lg for _, lg in steps]])
        by_hand = sum(move_time(a, b, TIMING) for a, b in itertools.pairwise(legs))
        assert costs.time_s[k] == pytest.approx(by_hand)
        assert costs.n_moves[k] == len(steps)
        assert costs.travel_mm[k] == pytest.approx(np.abs(np.diff(legs, axis=0)).max(axis=1).sum())


def test_repeat_costs_retreat_approach_target(robot):
    geom = Geometry.nominal(robot)
    cost = move_costs(geom, robot.home, robot.home, MotionRules(50.0, 2.0, 10.0), TIMING)
    # retreat 10 mm, back up 8 mm to the approach point, 2 mm to the target: all triangular profiles.
    expected = sum(2 * math.sqrt(d / 100.0) for d in (10.0, 8.0, 2.0)) + 3 * 0.25
    assert cost.time_s[0] == pytest.approx(expected)
    assert cost.travel_mm[0] == pytest.approx(20.0)


def test_route_estimate_adds_up(robot, rng):
    geom = Geometry.nominal(robot)
    measure, verify = feasible_random_poses(robot, 5, rng), feasible_random_poses(robot, 3, rng)
    est = estimate_route(geom, robot.home, calibration_phases(measure, verify), MotionRules(), TIMING, robot.home)
    assert [p.phase for p in est.phases] == ["measure", "verify", "verify_after", "return_home"]
    assert est.settle_s == pytest.approx((5 + 3 + 3) * 2.0)
    assert est.probing_s == pytest.approx((5 + 3 + 3) * 30.0)
    assert est.total_s == pytest.approx(est.motion_s + est.settle_s + est.probing_s)
    route = np.vstack([robot.home, measure, verify, verify])
    motion = move_costs(geom, route[:-1], route[1:], MotionRules(), TIMING).time_s.sum()
    back = move_costs(geom, verify[-1], robot.home, MotionRules(), TIMING, approach=False).time_s[0]
    assert est.motion_s == pytest.approx(motion + back)
    assert est.phase("return_home").settle_s == 0.0
    assert set(est.as_dict()["phases"]) == {"measure", "verify", "verify_after", "return_home"}


def test_repeatable_pose_needs_room_for_the_retreat(robot, rng):
    geom = Geometry.nominal(robot)
    poses = feasible_random_poses(robot, 10, rng)
    k = repeatable_pose(geom, poses, robot.leg_limits[0], MotionRules())
    margins = inverse_kinematics(geom, poses).min(axis=1) - robot.leg_limits[0]
    assert margins[k] == margins.max()
    with pytest.raises(ValueError, match="retreat"):
        repeatable_pose(geom, poses, robot.leg_limits[0] + margins.max(), MotionRules())


def test_format_minutes():
    assert format_minutes(42) == "42 s"
    assert format_minutes(750) == "12.5 min"
    assert format_minutes(3599.9) == "60.0 min"
    assert format_minutes(2 * 3600 + 59.9 * 60) == "3 h 00 min"
