"""Compensation: full geometry upload removes the identified error; offsets alone leave a documented rest."""

from __future__ import annotations

import numpy as np
import pytest

from hilcal.compensation import ControllerGeometry, compensate, plausibility
from hilcal.identification import identify
from hilcal.kinematics import Geometry, forward_kinematics, inverse_kinematics
from hilcal.metrics import AccuracySummary
from hilcal.planning import design
from sim_devices.rig.config import load_errors


@pytest.fixture(scope="module")
def identified(robot):
    """An exact identification of the Table 2 errors from noise-free data (hilcal's own model is not used)."""
    truth = load_errors("table2", robot).to_vector()
    poses = design.verification_poses(robot, 40, 3)
    nominal = Geometry.nominal(robot)
    legs = inverse_kinematics(nominal, poses)
    true_poses = forward_kinematics(nominal.perturbed(truth), legs, poses)
    return truth, identify(robot, legs, true_poses)


def _reached(robot, truth, before: ControllerGeometry, after: ControllerGeometry, poses):
    """Independent check: where the real platform goes when `after` commands `poses`."""
    d = truth.reshape(6, 7)
    setpoints = inverse_kinematics(Geometry(after.a, after.b), poses)
    strokes = setpoints - after.l0
    geometric = strokes + before.l0 + d[:, 6]
    return forward_kinematics(Geometry(robot.a + d[:, 0:3], robot.b + d[:, 3:6]), geometric, poses)


def test_full_compensation_reaches_the_commanded_poses(robot, identified):
    truth, ident = identified
    before = ControllerGeometry(robot.a, robot.b, robot.l0)
    samples = design.verification_poses(robot, 30, 9)
    comp = compensate(robot, before, ident, offsets_only=False, sample_poses=samples)
    assert comp.mode == "full" and comp.uncompensated is None
    reached = _reached(robot, truth, before, comp.parameters, samples)
    assert AccuracySummary.of(reached, samples).position_mm.max < 1e-4


def test_offsets_only_is_better_than_nothing_and_reports_the_rest(robot, identified):
    truth, ident = identified
    before = ControllerGeometry(robot.a, robot.b, robot.l0)
    samples = design.verification_poses(robot, 30, 9)
    comp = compensate(robot, before, ident, offsets_only=True, sample_poses=samples)
    assert comp.mode == "offsets_only"
    np.testing.assert_array_equal(comp.parameters.a, robot.a)
    raw = AccuracySummary.of(_reached(robot, truth, before, before, samples), samples).position_mm.rms
    rest = AccuracySummary.of(_reached(robot, truth, before, comp.parameters, samples), samples).position_mm.rms
    assert rest < 0.7 * raw
    assert comp.uncompensated.position_mm.rms == pytest.approx(rest, rel=1e-3)


def test_plausibility_flags_implausible_sets(robot, identified):
    _, ident = identified
    assert plausibility(ident) == []
    wild = ident.__class__(**{**ident.__dict__, "x": ident.x + np.r_[np.zeros(6), 25.0, np.zeros(35)]})
    problems = plausibility(wild)
    assert any("leg1_dl0_mm" in p and "exceeds" in p for p in problems)
