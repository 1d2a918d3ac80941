"""The parts of missing-physics discovery: sessions and motion history, the noise yardstick, the min-P tests."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from hilcal.discovery.context import EffectContext, detect_sessions, joint_angles, motion_history
from hilcal.discovery.generic_terms import bspline_basis, generic_groups
from hilcal.discovery.noise import (
    find_repeats,
    noise_from_repeats,
    revisited_poses,
    sigma_from_sphere_fit,
    sphere_noise_covariance,
)
from hilcal.discovery.regression import orth
from hilcal.discovery.selection import ModelState, assess
from hilcal.discovery.term_groups import GENERIC, TermGroup
from hilcal.planning import design
from hilcal.pose_measurement import pose_from_spheres, rigid_fit
from hilcal.recording import recording_from_arrays
from tests.poses import feasible_random_poses


def test_sessions_start_at_a_clock_reset_or_a_long_pause():
    t = np.array([0.0, 60, 120, 120 + 5 * 3600, 5 * 3600 + 200, 10.0, 70])
    assert detect_sessions(t).tolist() == [0, 0, 0, 1, 1, 2, 2]


def test_motion_history_is_unknown_at_each_session_start():
    legs = np.tile(np.array([[100.0], [101.0], [100.5], [100.5], [102.0], [90.0]]), (1, 6))
    session = np.array([0, 0, 0, 0, 1, 1])
    direction, size = motion_history(legs, session)
    assert direction[:, 0].tolist() == [0, 1, -1, -1, 0, -1]
    assert np.isnan(size[0, 0]) and np.isnan(size[4, 0])
    assert size[1:4, 0].tolist() == [1.0, 0.5, 0.5]


def test_a_pose_measured_again_keeps_the_direction_whatever_its_readings_noise():
    # one leg extends to 101 mm, then the pose is measured three more times in a row: readings 3 µm apart either way
    legs = np.tile(np.array([[100.0], [101.0], [100.997], [101.003], [100.998]]), (1, 6))
    cmd = np.repeat(np.array([[0.0] * 6, [1.0] + [0.0] * 5]), [1, 4], axis=0)
    session = np.zeros(5, dtype=int)
    direction, size = motion_history(legs, session, cmd)
    assert direction[:, 0].tolist() == [0, 1, 1, 1, 1]
    assert np.allclose(size[1:, 0], 1.0)
    noisy, _ = motion_history(legs, session)  # without the commanded poses, the noise reads as moves
    assert noisy[:, 0].tolist() == [0, 1, -1, 1, -1]


def test_spline_basis_is_a_partition_of_unity_and_clamps():
    x = np.linspace(-5, 15, 41)
    B = bspline_basis(x, 0.0, 10.0, np.array([3.0, 6.0]))
    assert B.shape == (41, 6)
    np.testing.assert_allclose(B.sum(axis=1), 1.0, atol=1e-12)
    np.testing.assert_allclose(B[0], B[10])


def _registration_rms(robot, sigma, rng, n):
    """Simulated sphere measurements at home: per-row max of the two registration RMS values (our column)."""
    plat = robot.platform_spheres[None] + robot.home[:3] + rng.normal(0, sigma, (n, *robot.platform_spheres.shape))
    base = robot.base_spheres[None] + rng.normal(0, sigma, (n, *robot.base_spheres.shape))
    rms_p = rigid_fit(robot.platform_spheres, plat)[2]
    rms_b = rigid_fit(robot.base_spheres, base)[2]
    return np.maximum(rms_p, rms_b)


def test_sphere_fit_column_recovers_the_sphere_noise(robot):
    rng = np.random.default_rng(3)
    sigma, dof = sigma_from_sphere_fit(_registration_rms(robot, 0.004, rng, 4000), robot)
    assert sigma == pytest.approx(0.004, rel=0.03)
    assert dof > 1000


def test_propagated_pose_covariance_matches_monte_carlo(robot):
    rng = np.random.default_rng(4)
    pose = np.array([50.0, -30.0, 3100.0, 2.0, -3.0, 4.0])
    cov = sphere_noise_covariance(robot, pose[None], 0.005, robot.characteristic_length_mm)[0]
    from hilcal.error_models import pose_difference
    from hilcal.kinematics import split_pose

    R, t = split_pose(pose)
    plat = robot.platform_spheres @ R.T + t
    n = 20000
    noisy = pose_from_spheres(plat + rng.normal(0, 0.005, (n, *plat.shape)),
                              robot.base_spheres + rng.normal(0, 0.005, (n, *robot.base_spheres.shape)), robot).pose
    d = pose_difference(noisy, np.broadcast_to(pose, noisy.shape), robot.characteristic_length_mm)
    mc = d.T @ d / n
    np.testing.assert_allclose(np.diag(cov), np.diag(mc), rtol=0.06)


def test_repeats_are_found_by_legs_without_commanded_poses(robot):
    legs = np.array([[4300.0] * 6, [4310.0] * 6, [4300.0] * 6, [4300.002] * 6, [4320.0] * 6,
                     [4300.0] * 6, [4310.0] * 6, [4330.0] * 6, [4340.0] * 6, [4350.0] * 6])
    meas = np.tile(robot.home, (10, 1))
    rec = recording_from_arrays(np.arange(1, 11), ["measure"] * 10, np.arange(10) * 60.0, None, legs, meas,
                                min_measure_rows=1)
    groups = find_repeats(rec)
    assert [g.tolist() for g in groups] == [[0, 2, 3, 5], [1, 6]]
    residuals = np.random.default_rng(0).normal(0, 0.01, (10, 6))
    cov, dof = noise_from_repeats(residuals, groups)
    assert dof == 4 and cov.shape == (6, 6)


def test_repeats_of_a_commanded_pose_allow_the_servo_s_scatter_but_not_hours_between_visits(robot):
    """A real servo lands within µm to tens of µm: visits of one commanded pose minutes apart are repeats even when
    their legs differ by 20 µm; visits two hours apart (drift between them) and a landing 0.2 mm off are not."""
    cmd = np.tile(robot.home, (7, 1))
    cmd[3:5, 0] += 50.0  # a second pose, visited at t = 100 s and two hours later
    cmd[5:7, 1] += 50.0  # a third, whose second landing is 0.2 mm off on one leg
    legs = np.full((7, 6), 4300.0)
    legs[1, 2] += 0.012
    legs[2, 4] -= 0.020
    legs[6, 0] += 0.2
    time_s = np.array([0.0, 30.0, 60.0, 100.0, 7300.0, 7400.0, 7430.0])  # the second pose: two hours apart
    rec = recording_from_arrays(np.arange(1, 8), ["measure"] * 7, time_s, cmd, legs, np.tile(robot.home, (7, 1)),
                                min_measure_rows=1)
    groups = find_repeats(rec, np.zeros(7, dtype=int))
    assert [g.tolist() for g in groups] == [[0, 1, 2]]
    assert revisited_poses(rec, groups) == 2


def test_joint_angles_are_what_docs_diagnosis_tells_a_controller_to_compute(robot):
    """The recipe of docs/diagnosis.md (loadable corrections), written here with numpy: the controller that loads a
    joint-angle correction computes the same angles as the diagnosis."""
    poses = feasible_random_poses(robot, 5, np.random.default_rng(4))
    roll, pitch, yaw = np.radians(robot.home[3:])

    def rot(r: float, p: float, y: float) -> np.ndarray:
        cr, sr, cp, sp, cy, sy = np.cos(r), np.sin(r), np.cos(p), np.sin(p), np.cos(y), np.sin(y)
        return (np.array([[cy, -sy, 0], [sy, cy, 0], [0, 0, 1]]) @ np.array([[cp, 0, sp], [0, 1, 0], [-sp, 0, cp]])
                @ np.array([[1, 0, 0], [0, cr, -sr], [0, sr, cr]]))

    def unit_legs(R: np.ndarray, t: np.ndarray) -> np.ndarray:
        v = robot.a @ R.T + t - robot.b
        return v / np.linalg.norm(v, axis=1, keepdims=True)

    def frame(d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        up = np.array([0.0, 0.0, 1.0]) if abs(d[2]) < 0.9 else np.array([1.0, 0.0, 0.0])
        e1 = np.cross(up, d) / np.linalg.norm(np.cross(up, d))
        return e1, np.cross(d, e1)

    R0 = rot(roll, pitch, yaw)
    d0 = unit_legs(R0, robot.home[:3])
    base, platform = joint_angles(robot, poses)
    for n, q in enumerate(poses):
        R = rot(*np.radians(q[3:]))
        u = unit_legs(R, q[:3])
        for i in range(6):
            e1, e2 = frame(d0[i])
            f1, f2 = frame(R0.T @ d0[i])
            np.testing.assert_allclose(base[n, i], [u[i] @ e1, u[i] @ e2], atol=1e-12)
            np.testing.assert_allclose(platform[n, i], [R.T @ u[i] @ f1, R.T @ u[i] @ f2], atol=1e-12)


def _null_state(rng, n_poses=30, p=20):
    J = rng.normal(size=(6 * n_poses, p))
    r = rng.normal(size=6 * n_poses)
    return ModelState.build(r, J, np.eye(6), n_poses, np.arange(n_poses))


def _random_groups(rng, n_poses, k):
    groups = [TermGroup(f"g{j}", GENERIC, "unexplained", "g", ("a", "b"), lambda c: None) for j in range(k)]
    return groups, [rng.normal(size=(6 * n_poses, 2)) for _ in range(k)]


def test_min_p_keeps_the_family_wise_false_alarm_rate_under_the_null():
    """Pure noise, 25 candidate groups: the chance that any adjusted p falls below alpha stays near alpha."""
    rng = np.random.default_rng(7)
    hits = 0
    trials = 200
    for _ in range(trials):
        state = _null_state(rng)
        groups, columns = _random_groups(rng, 30, 25)
        tests = assess(state, groups, columns, 0.10, 199, int(rng.integers(1 << 30)))
        hits += any(t.significant for t in tests)
    assert 0.04 <= hits / trials <= 0.14


def test_min_p_finds_a_real_group_among_many():
    rng = np.random.default_rng(8)
    state = _null_state(rng)
    groups, columns = _random_groups(rng, 30, 25)
    signal = orth(columns[3] - state.Q @ (state.Q.T @ columns[3]))[:, 0] * 8.0
    state = dataclasses.replace(state, r0=state.r0 + signal)
    tests = assess(state, groups, columns, 0.05, 199, 1)
    assert [t.group.key for t in tests if t.significant] == ["g3"]


def test_generic_groups_cover_every_leg_and_variable(robot):
    poses = design.verification_poses(robot, 40, 1)
    ctx = EffectContext.at_poses(robot, poses)
    ctx = dataclasses.replace(ctx, session_time_s=np.arange(40) * 60.0, time_s=np.arange(40) * 60.0)
    groups = generic_groups(ctx)
    variables = {(g.leg, g.variable) for g in groups}
    for leg in range(6):
        for var in ("stroke", "stroke_cyclic", "base_joint_angle", "platform_joint_angle", "axial_force", "time"):
            assert (leg, var) in variables
    assert len({g.key for g in groups}) == len(groups)
    shared = {g.key.split(":")[1] for g in groups if g.leg is None}
    assert shared == {"axial_force", "stroke", "time", "stroke_cyclic", "base_joint_angle", "platform_joint_angle"}
    for g in [g for g in groups if g.leg is None]:
        phi = g.phi(ctx)
        q = g.n_params // 6
        for leg in range(6):
            cols = g.leg_columns(leg)
            assert cols.size == q
            others = [i for i in range(6) if i != leg]
            assert np.all(phi[:, others][:, :, cols] == 0)
    for g in [g for g in groups if g.leg is not None][:50]:
        phi = g.phi(ctx)
        assert phi.shape == (40, 6, g.n_params)
        assert np.all(phi[:, [i for i in range(6) if i != g.leg], :] == 0)


def test_the_shared_stroke_quadratic_lends_a_bent_transducer_no_scale(robot):
    """A transducer bent by 0.25 mm, level at both ends of its stroke (end-point linearity), on poses that reach one
    end of the stroke more than the other. Fitted with a leg offset, a scale and the shared stroke quadratic, the
    quadratic about the middle of the robot file's stroke limits leaves the scale near nothing; one about the middle
    of the recorded strokes lends it the bow's slope over the offset between the two middles."""
    lo, hi = robot.leg_limits[0] - robot.l0, robot.leg_limits[1] - robot.l0
    poses = feasible_random_poses(robot, 600, np.random.default_rng(4))
    low = np.all(EffectContext.at_poses(robot, poses).stroke_mm < lo + 0.75 * (hi - lo), axis=1)
    ctx = EffectContext.at_poses(robot, poses[low][:60])
    s = ctx.stroke_mm
    bow = 0.25 * np.sin(np.pi * (s - lo) / (hi - lo))
    recorded_middle = (s.min(axis=0) + s.max(axis=0)) / 2.0
    assert np.min(np.abs(recorded_middle - (lo + hi) / 2.0)) > 5.0  # the poses are off the stroke's middle

    def scale_ppm(groups: list) -> np.ndarray:
        quadratic = next(g for g in groups if g.key == "all:stroke:quadratic").phi(ctx)
        out = []
        for i in range(6):
            X = np.column_stack([np.ones(len(s)), s[:, i], quadratic[:, i, i]])
            out.append(np.linalg.lstsq(X, bow[:, i], rcond=None)[0][1] * 1e6)
        return np.abs(np.array(out))

    at_limits = scale_ppm(generic_groups(ctx, (lo, hi)))
    at_recorded = scale_ppm(generic_groups(ctx))
    assert at_limits.max() < 10.0
    assert at_recorded.min() > 10.0 * at_limits.max()
