"""The rig's generic per-leg effect (tables and joint curvatures), a recorded temperature history, the replay of a
recording, and the TOML the twin is written in: checked against values worked out here, not by the rig's code.
"""

from __future__ import annotations

import numpy as np
import pytest
from pydantic import ValidationError

from hilcal.planning.design import verification_poses
from hilcal.robot import rotation_matrix
from procedures.cli.simulated_recording import RecordingOptions, simulate_with_truth
from sim_devices.rig.config import EffectsConfig, GeometryErrors, RigConfig, TemperatureConfig, errors_toml, load_errors
from sim_devices.rig.replay import replay_poses
from sim_devices.rig.rig import SimulatedRig
from sim_devices.rig.table_config import LegTablesConfig
from sim_devices.sim_config import load_sim_config, sim_config_toml

POSE = np.array([10.0, -15.0, 3.0, 1.0, -2.0, 3.0])


def _rig(robot, tables=(), curvatures=(), temperature=None) -> SimulatedRig:
    effects = EffectsConfig(leg_tables=LegTablesConfig(enabled=True, tables=list(tables), curvatures=list(curvatures)))
    extra = {} if temperature is None else {"temperature": temperature}
    return SimulatedRig(robot, RigConfig(seed=1, errors=load_errors("table2", robot), effects=effects,
                                         leg_resolution_mm=0.0, **extra))


def test_a_stroke_table_adds_its_interpolated_value_to_its_leg_only(robot):
    table = {"leg": 3, "variable": "stroke_mm", "x": [0.0, 500.0, 1000.0], "correction_mm": [0.0, 0.04, -0.02]}
    rig = _rig(robot, [table])
    rig.move_to_lengths(rig.controller_ik(robot.home + POSE))
    stroke = rig.reported_lengths()[2] - robot.l0[2]
    want = 0.04 + (stroke - 500.0) / 500.0 * -0.06 if stroke > 500.0 else stroke / 500.0 * 0.04
    got = rig.length_corrections_mm()["leg_tables"]
    assert got[2] == pytest.approx(want, abs=1e-12)
    assert np.all(got[[0, 1, 3, 4, 5]] == 0.0)


def test_a_table_holds_its_end_values_and_a_session_table_follows_the_power_ons(robot):
    rig = _rig(robot, [{"leg": 1, "variable": "session", "x": [0.0, 1.0], "correction_mm": [0.0, 0.005]},
                       {"leg": 2, "variable": "session_time_s", "x": [0.0, 100.0], "correction_mm": [0.0, 0.01]}])
    rig.move_to_lengths(rig.controller_ik(robot.home + POSE))
    rig.advance_time(50.0)
    assert rig.length_corrections_mm()["leg_tables"][:2] == pytest.approx([0.0, 0.005])
    rig.advance_time(1000.0)
    assert rig.length_corrections_mm()["leg_tables"][:2] == pytest.approx([0.0, 0.01])
    rig.start_session()
    rig.start_session()
    assert rig.length_corrections_mm()["leg_tables"][:2] == pytest.approx([0.005, 0.0])


def test_a_joint_curvature_is_quadratic_in_the_leg_direction_on_its_axes(robot):
    axes = (np.array([1.0, 0.0, 0.0]), np.array([0.0, 1.0, 0.0]))
    curve = {"leg": 5, "joint": "base", "axis1": axes[0].tolist(), "axis2": axes[1].tolist(),
             "mm_per_rad2": [0.3, -0.2, 0.1]}
    rig = _rig(robot, curvatures=[curve])
    rig.move_to_lengths(rig.controller_ik(robot.home + POSE))
    pose = rig.true_pose()
    errors = load_errors("table2", robot)
    da, db, _ = errors.as_arrays()
    joint = rotation_matrix(np.radians(pose[3:])) @ (robot.a[4] + da[4]) + pose[:3]
    u = joint - (robot.b[4] + db[4])
    u /= np.linalg.norm(u)
    a1, a2 = u @ axes[0], u @ axes[1]
    assert rig.length_corrections_mm()["leg_tables"][4] == pytest.approx(0.3 * a1 * a1 - 0.2 * a1 * a2 + 0.1 * a2 * a2,
                                                                          abs=1e-12)


def test_a_recorded_temperature_history_replaces_the_drift_model(robot):
    rig = _rig(robot, temperature=TemperatureConfig(table_time_s=[0.0, 100.0], table_c=[20.0, 22.0]))
    rig.advance_time(25.0)
    assert rig.true_temperature_c() == pytest.approx(20.5)
    rig.advance_time(1000.0)
    assert rig.true_temperature_c() == pytest.approx(22.0)


@pytest.mark.parametrize("bad", [
    {"leg": 7, "variable": "stroke_mm", "x": [0.0, 1.0], "correction_mm": [0.0, 1.0]},
    {"leg": 1, "variable": "stroke_mm", "x": [1.0, 0.0], "correction_mm": [0.0, 1.0]},
    {"leg": 1, "variable": "stroke_mm", "x": [0.0, 1.0], "correction_mm": [0.0]},
    {"leg": 1, "variable": "speed", "x": [0.0, 1.0], "correction_mm": [0.0, 1.0]},
])
def test_a_bad_table_is_refused(bad):
    with pytest.raises(ValidationError):
        LegTablesConfig(enabled=True, tables=[bad])


def test_the_replay_reaches_the_rigs_own_poses_across_sessions(robot):
    """A rig whose physics depends on the stroke, the load and the session, recorded over two sessions: replaying its
    reported legs in order, with a power-on where the recording's clock starts a new session, gives its true poses.
    (What the recording does not hold, the power-on time and the motion before a session, is not in this rig.)"""
    effects = {"leg_compliance": {"enabled": True}, "sensor_scale": {"enabled": True}, "leg_tables": {
        "enabled": True, "tables": [
            {"leg": 2, "variable": "stroke_mm", "x": [0.0, 1000.0], "correction_mm": [0.0, 0.03]},
            {"leg": 4, "variable": "session", "x": [0.0, 1.0], "correction_mm": [0.0, -0.02]}]}}
    config = RigConfig(seed=3, errors=load_errors("table2", robot), effects=EffectsConfig.model_validate(effects),
                       temperature=TemperatureConfig(t0_c=20.0, drift_k_per_h=0.0, amplitude_k=0.0))
    poses = verification_poses(robot, 16, 0)
    rec, truth = simulate_with_truth(robot, config, poses[:10], poses[10:],
                                     options=RecordingOptions(session_gap_s=86400.0, include_temp=False))
    replayed = replay_poses(robot, config, rec.time_s, rec.legs_mm)
    np.testing.assert_allclose(replayed, truth, atol=1e-7)


def test_errors_and_a_twin_configuration_read_back_as_written(robot, tmp_path):
    errors = GeometryErrors.from_vector(np.random.default_rng(5).normal(0.0, 0.3, 42))
    (tmp_path / "errors.toml").write_text(errors_toml(errors, "a header\nof two lines"))
    assert load_errors(tmp_path / "errors.toml", robot) == errors
    data = {"rig": {"seed": 4, "errors": "errors.toml", "cmm_noise_mm": 0.002, "effects": {"leg_tables": {
        "enabled": True, "tables": [{"leg": 1, "variable": "stroke_mm", "x": [0.0, 1.0], "correction_mm": [0.0, 0.1]},
                                    {"leg": 6, "variable": "session", "x": [0.0], "correction_mm": [0.0]}],
        "curvatures": [{"leg": 2, "joint": "platform", "axis1": [1.0, 0.0, 0.0], "axis2": [0.0, 0.0, 1.0],
                        "mm_per_rad2": [1.0, 2.0, 3.0]}]}}}}
    (tmp_path / "sim.toml").write_text(sim_config_toml(data, "twin"))
    rig = load_sim_config(tmp_path / "sim.toml").rig.rig_config(robot)
    assert rig.errors == errors and rig.cmm_noise_mm == 0.002
    assert rig.effects.leg_tables.model_dump() == LegTablesConfig.model_validate(
        data["rig"]["effects"]["leg_tables"]).model_dump()
