"""Measured leg loads (leg1_force_kn ... leg6_force_kn) replace the statics of the robot file's mass: with a robot
file whose moving mass is half the real one, the compliance read through statics comes out about twice too large;
with the machine's own loads it is the simulated one."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from hilcal.discovery.context import EffectContext
from hilcal.discovery.search import diagnose
from hilcal.kinematics import Geometry, gravity_wrench, inverse_kinematics, leg_forces
from hilcal.planning import design
from hilcal.recording import FORCE_COLUMNS, recording_from_arrays
from hilcal.robot import Robot
from procedures.cli.simulated_recording import simulate_with_truth
from sim_devices.rig.config import EffectsConfig, RigConfig, concealed_effect_config, load_errors
from tests.poses import default_design, feasible_random_poses

SEED = 2026


def _statics_kn(robot: Robot, poses: np.ndarray) -> np.ndarray:
    return leg_forces(Geometry.nominal(robot), poses, gravity_wrench(robot, poses)) / 1000.0


def test_the_context_takes_measured_loads_where_a_row_has_all_six(robot: Robot) -> None:
    poses = feasible_random_poses(robot, 5, np.random.default_rng(1))
    forces = np.arange(30.0).reshape(5, 6)
    forces[2, 3] = np.nan  # this row has no load on leg 4: the statics stand for the whole row
    rec = recording_from_arrays(np.arange(1, 6), ["measure"] * 5, np.arange(5) * 60.0, None,
                                inverse_kinematics(Geometry.nominal(robot), poses), poses,
                                extra={name: forces[:, k] for k, name in enumerate(FORCE_COLUMNS)},
                                min_measure_rows=1)
    ctx = EffectContext.from_recording(rec, robot)
    kept = [0, 1, 3, 4]
    np.testing.assert_array_equal(ctx.force_kn[kept], forces[kept])
    np.testing.assert_allclose(ctx.force_kn[2], _statics_kn(robot, poses[2:3])[0])


def _half_mass(robot: Robot) -> Robot:
    mass = robot.spec.mass.model_copy(update={"moving_mass_kg": robot.moving_mass_kg / 2.0})
    return Robot(robot.spec.model_copy(update={"mass": mass}))


@pytest.mark.slow
def test_measured_loads_overrule_a_wrong_mass_in_the_robot_file(robot: Robot) -> None:
    effect = concealed_effect_config("leg_compliance", 1.0, SEED).leg_compliance
    config = RigConfig(seed=SEED, errors=load_errors("table2", robot),
                       effects=EffectsConfig.model_validate({"leg_compliance": effect}))
    rec, _ = simulate_with_truth(robot, config, default_design(32, 0), design.verification_poses(robot, 24, SEED))
    truth_um = np.asarray(effect.c_mm_per_kn) * 1000.0
    light = _half_mass(robot)

    def compliance_um(diag) -> np.ndarray:
        assert "leg_compliance" in diag.effects, diag.explanation
        return np.array([diag.parameters[f"leg{i}_leg_compliance_um_per_kN"] for i in range(1, 7)])

    through_statics = compliance_um(diagnose(rec, light))
    assert np.median(through_statics / truth_um) == pytest.approx(2.0, rel=0.2)
    # the machine's loads: the real mass's statics at the measured poses, as a pressure logger would give them
    loads = _statics_kn(robot, rec.meas)
    measured = dataclasses.replace(rec, extra={**rec.extra, **{n: loads[:, k] for k, n in enumerate(FORCE_COLUMNS)}})
    np.testing.assert_allclose(compliance_um(diagnose(measured, light)), truth_um, rtol=0.25)
