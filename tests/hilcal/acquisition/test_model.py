"""The acquisition model against the simulated rig's truth physics (written apart from hilcal): a machine with a
gross reading-scale fault, joint errors three times the paper's and leg compliance it does not model. Its predictions
must carry their error within their bound from the first pose on, and be sub-millimetre after a few poses."""

from __future__ import annotations

import numpy as np
import pytest

from hilcal.acquisition.model import Priors, predict, prior_belief, update
from hilcal.acquisition.spheres import COVERAGE_K
from hilcal.kinematics import Geometry, inverse_kinematics
from hilcal.robot import default_robot
from hilcal.workspace import random_poses
from sim_devices.rig.config import (
    EffectsConfig,
    GeometryErrors,
    LegComplianceConfig,
    RigConfig,
    SensorScaleConfig,
)
from sim_devices.rig.rig import SimulatedRig

ROBOT = default_robot()


def _rig(gain_ppm: list[float], joint_sd_mm: float, seed: int) -> SimulatedRig:
    errors = GeometryErrors.from_vector(np.random.default_rng(seed).normal(0.0, joint_sd_mm, 42))
    effects = EffectsConfig(sensor_scale=SensorScaleConfig(enabled=True, gain_error_ppm=gain_ppm),
                            leg_compliance=LegComplianceConfig(enabled=True))
    return SimulatedRig(ROBOT, RigConfig(seed=seed, errors=errors, effects=effects, cmm_noise_mm=0.003))


@pytest.mark.parametrize(("gain", "joint_sd_mm"), [(0.04, 3.0), (-0.09, 2.0)])
def test_predictions_hold_their_bound_and_converge(gain: float, joint_sd_mm: float) -> None:
    rig = _rig([0.0, 0.0, 0.0, gain * 1e6, 0.0, 0.0], joint_sd_mm, seed=3)
    poses = random_poses(ROBOT, 30, np.random.default_rng(5))
    nominal = Geometry.nominal(ROBOT)
    belief = prior_belief(ROBOT.a, ROBOT.b, ROBOT.l0, Priors.of(ROBOT))
    rng = np.random.default_rng(9)
    errors, bounds = [], []
    guess = ROBOT.home
    for cmd in poses:
        rig.move_to_lengths(inverse_kinematics(nominal, cmd))
        truth = rig.true_pose()
        pred = predict(belief, rig.reported_lengths(), guess)
        errors.append(float(np.linalg.norm(truth[:3] - pred.pose[:3])))
        bounds.append(COVERAGE_K * pred.position_sd_mm)
        measured = truth + np.concatenate([rng.normal(0.0, 0.003, 3), rng.normal(0.0, 2e-5, 3)])
        belief = update(belief, rig.reported_lengths(), measured)
        guess = measured
    errors, bounds = np.array(errors), np.array(bounds)
    assert errors[0] > 5.0, "the planted errors should put the first pose far from the nominal prediction"
    assert np.all(errors < bounds), list(zip(errors.round(3), bounds.round(3), strict=True))
    assert np.all(errors[8:] < 0.5) and np.all(bounds[8:] < 1.0)
    # the reading scale is found: g = 1/(1 + k) - 1 for the leg with the fault, the others near zero
    assert belief.reading_gain()[3] == pytest.approx(gain, abs=0.002)
    assert np.max(np.abs(np.delete(belief.reading_gain(), 3))) < 0.002


def test_physical_lengths_undo_the_reading_scale() -> None:
    belief = prior_belief(ROBOT.a, ROBOT.b, ROBOT.l0, Priors.of(ROBOT))
    x = belief.x.copy()
    x[7] = 1.0 / (1.0 - 0.09) - 1.0  # leg 1 reads 9 % short: k = 1/(1 + g) - 1 with g = -0.09
    shifted = type(belief)(**{**belief.__dict__, "x": x})
    legs = ROBOT.l0 + 900.0
    physical = shifted.physical_lengths_mm(legs)
    assert physical[0] == pytest.approx(ROBOT.l0[0] + 900.0 / 0.91)
    assert np.allclose(physical[1:], legs[1:])
