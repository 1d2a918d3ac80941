"""When a sequential plan may stop (hilcal.planning.stopping): the accuracy rule, the diagnosis' minimum, the
physics screening and the library efficiency."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from hilcal.planning.candidates import library_columns, library_variables
from hilcal.planning.design import pose_jacobians
from hilcal.planning.prediction import PoseNoise, VerifyPrediction
from hilcal.planning.stopping import (
    MinimumSettings,
    accuracy_rule,
    diagnosis_minimum,
    library_efficiency,
    library_information,
    screen,
)
from tests.poses import feasible_random_poses

NOISE = PoseNoise.isotropic(0.005, 0.005, 9, 9, "test")


def _prediction(upper_mm: float) -> VerifyPrediction:
    return VerifyPrediction(20, upper_mm / 2, upper_mm / 3, upper_mm, 0.001, 0.01, 0.95, NOISE)


def test_target_rule():
    assert accuracy_rule(_prediction(0.030), None, 3, 0.032, 0.02).kind == "target"
    check = accuracy_rule(_prediction(0.033), _prediction(0.050), 3, 0.032, 0.02)
    assert not check.met and "target 32.0 µm" in check.sentence


def test_improvement_rule_averages_over_the_window():
    # (0.0300 - 0.0285) / 0.0300 / 3 = 1.67 % per row: below 2 %, above 1 %
    assert accuracy_rule(_prediction(0.0285), _prediction(0.0300), 3, None, 0.02).kind == "converged"
    slow = accuracy_rule(_prediction(0.0285), _prediction(0.0300), 3, None, 0.01)
    assert not slow.met and slow.improvement_per_row == pytest.approx(0.0166667, rel=1e-4)
    assert not accuracy_rule(_prediction(0.03), None, 3, None, 0.02).met
    assert not accuracy_rule(None, None, 3, None, 0.02).met


def test_minimum_names_what_is_missing():
    rng = np.random.default_rng(0)
    load, stroke = rng.uniform(4, 14, (9, 6)), rng.uniform(0, 1, (9, 6))
    settings = MinimumSettings(repeat_rows=4, library_efficiency=0.2, residual_dof=30)
    short = diagnosis_minimum(9, 2, 0.1, load, stroke, np.array([[10.0] * 6, [1.0] * 6]), settings)
    assert not short.met and len(short.missing) == 3
    assert "measured 2 of 4 times" in short.missing[0] and "0.10 of the fixed plan" in short.missing[1]
    assert short.residual_dof == 6 * 9 - 54
    ok = diagnosis_minimum(14, 4, 0.25, load, stroke, np.array([[10.0] * 6, [1.0] * 6]), settings)
    assert ok.met and ok.library_met and not ok.missing


def test_library_efficiency_counts_information(robot, rng):
    poses = feasible_random_poses(robot, 20, rng)
    J = pose_jacobians(robot, poses)
    info = library_information(J, library_columns(J, *library_variables(robot, poses)))
    assert library_efficiency(info, info) == pytest.approx(1.0)
    twice = np.concatenate([poses, poses])
    J2 = pose_jacobians(robot, twice)
    info2 = library_information(J2, library_columns(J2, *library_variables(robot, twice)))
    assert library_efficiency(info2, info) == pytest.approx(2.0)


def test_leg_loads_carry_the_weight(robot, rng):
    poses = feasible_random_poses(robot, 5, rng)
    load, stroke = library_variables(robot, poses)
    R = Rotation.from_euler("ZYX", poses[:, [5, 4, 3]], degrees=True).as_matrix()
    legs = np.einsum("nij,kj->nki", R, robot.a) + poses[:, None, :3] - robot.b
    up = (legs / np.linalg.norm(legs, axis=-1, keepdims=True))[..., 2]
    np.testing.assert_allclose(np.sum(load * up, axis=1), robot.moving_mass_kg * robot.gravity_mps2 / 1000, rtol=1e-9)
    lengths = np.linalg.norm(legs, axis=-1)
    np.testing.assert_allclose(stroke, (lengths - robot.l0) / 1000, rtol=1e-9)


def _screening_data(robot, rng, n=16, load_effect=0.0, sigma=0.005):
    """Residuals of a linearized geometric fit to noise (and a leg-load effect): what a fit leaves."""
    poses = feasible_random_poses(robot, n, rng)
    rows = np.vstack([np.repeat(poses[:1], 3, axis=0), poses])
    J = pose_jacobians(robot, rows)
    library = library_columns(J, *library_variables(robot, rows))
    y = rng.normal(0.0, sigma, (len(rows), 6)) + load_effect * library[..., :6].sum(axis=-1)
    A = J.reshape(-1, 42)
    r = y.reshape(-1) - A @ np.linalg.lstsq(A, y.reshape(-1), rcond=None)[0]
    first = y[:4] - y[:4].mean(axis=0)
    return r.reshape(-1, 6), J, library, first


def test_screening_keeps_its_level_and_finds_a_load_effect(robot):
    rng = np.random.default_rng(11)
    alarms = 0
    for _ in range(150):
        r, J, lib, dev = _screening_data(robot, rng)
        alarms += screen(r, J, lib, dev, PoseNoise.isotropic(0.005, 0.005, 9, 9, "repeats"), 0.05).suspected
    assert alarms <= 16  # level 5 %: 7.5 expected, 16 or more has probability < 0.3 %
    r, J, lib, dev = _screening_data(robot, rng, load_effect=0.02)
    found = screen(r, J, lib, dev, PoseNoise.isotropic(0.005, 0.005, 9, 9, "repeats"), 0.05)
    assert found.suspected and found.p_load < 1e-4 and "signs of missing physics" in found.sentence()
