"""Compensation: full geometry upload removes the identified error; offsets alone leave a documented rest."""

from __future__ import annotations

import numpy as np
import pytest

from hilcal.compensation import ControllerGeometry, compensate, held_out_after, plausibility
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


def test_the_held_out_prediction_after_an_offsets_upload_is_where_the_platform_goes(robot, identified):
    """Held-out rows measured before the upload (noisy measured poses), then the offsets uploaded: the prediction is
    where the platform goes when the new set commands those poses (the truth's), plus each row's measurement noise
    as it was; with the full set, the noise alone."""
    truth, ident = identified
    before = ControllerGeometry(robot.a, robot.b, robot.l0)
    poses = design.verification_poses(robot, 12, 21)
    legs = inverse_kinematics(Geometry(before.a, before.b), poses)
    noise = np.random.default_rng(5).normal(0.0, [0.003] * 3 + [0.0002] * 3, poses.shape)
    measured = _reached(robot, truth, before, before, poses) + noise
    samples = design.verification_poses(robot, 30, 9)
    offsets = compensate(robot, before, ident, offsets_only=True, sample_poses=samples).parameters
    predicted = held_out_after(robot, before, ident.x, offsets, legs, measured, poses)
    expected = AccuracySummary.of(_reached(robot, truth, before, offsets, poses) + noise, poses)
    assert predicted.position_mm.max == pytest.approx(expected.position_mm.max, rel=1e-3)
    assert predicted.position_mm.rms == pytest.approx(expected.position_mm.rms, rel=1e-3)
    assert expected.position_mm.rms > 0.05, "the joints the controller keeps leave tenths of a mm"
    full = compensate(robot, before, ident, offsets_only=False, sample_poses=samples).parameters
    alone = held_out_after(robot, before, ident.x, full, legs, measured, poses)
    assert alone.position_mm.rms == pytest.approx(AccuracySummary.of(poses + noise, poses).position_mm.rms, rel=1e-3)


def test_plausibility_flags_implausible_sets(robot, identified):
    _, ident = identified
    assert plausibility(ident) == []
    wild = ident.__class__(**{**ident.__dict__, "x": ident.x + np.r_[np.zeros(6), 25.0, np.zeros(35)]})
    problems = plausibility(wild)
    assert any("leg1_dl0_mm" in p and "exceeds" in p for p in problems)
