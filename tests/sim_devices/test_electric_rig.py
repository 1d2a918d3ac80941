"""The rig's electric legs (motor encoder, homing, drive compliance) against values worked out here, and the
committed electric-hexapod example (examples/electric_hexapod) regenerated from its seeded generator.

Leg lengths at the rig's true pose are recomputed with hilcal.robot.rotation_matrix instead of the rig's scipy
rotations; leg loads by virtual work (numerical Jacobian of the leg lengths and of the height of the centre of mass)
instead of the rig's 6x6 equilibrium.
"""

from __future__ import annotations

import importlib.util
import math
import sys
from pathlib import Path
from types import ModuleType

import numpy as np
import pytest
from pydantic import ValidationError
from scipy.linalg import lstsq
from scipy.spatial.transform import Rotation

from hilcal.recording import read_recording, write_recording
from hilcal.robot import load_robot, rotation_matrix
from procedures.cli.simulated_recording import RecordingOptions, second_session_start_s, simulate_with_truth
from sim_devices.rig.config import EffectsConfig, RigConfig, random_errors
from sim_devices.rig.electric_config import (
    BALL_SCREW_C_PER_LENGTH_MM_PER_KN_M,
    DriveComplianceConfig,
    MotorEncoderConfig,
    drive_compliance_for_signature,
)
from sim_devices.rig.electric_physics import homing_offsets_mm
from sim_devices.rig.rig import SimulatedRig

EXAMPLE = Path(__file__).resolve().parents[2] / "examples" / "electric_hexapod"
ROBOT = load_robot(EXAMPLE / "robot.toml")
ERRORS = random_errors(5, 0.05)
DA, DB, DL0 = ERRORS.as_arrays()
A_TRUE, B_TRUE = ROBOT.a + DA, ROBOT.b + DB
RATIO = np.array([1.0625, 0.95, 1.0, 1.02, 0.9375, 1.0001])


def workspace_poses(n: int, seed: int) -> np.ndarray:
    """Poses in the central 70 % of the workspace box (leg lengths inside the limits)."""
    lo, hi = ROBOT.workspace.T
    mid, half = (lo + hi) / 2, (hi - lo) / 2 * 0.7
    return np.random.default_rng(seed).uniform(mid - half, mid + half, (n, 6))


def leg_lengths(pose: np.ndarray) -> np.ndarray:
    """|R a_i + t - b_i| of the true geometry."""
    R = rotation_matrix(np.radians(pose[3:]))
    return np.linalg.norm(A_TRUE @ R.T + pose[:3] - B_TRUE, axis=1)


def forces_by_virtual_work_kn(pose: np.ndarray) -> np.ndarray:
    """Axial compressions (kN) from J^T F = grad(m g z_com), J by Richardson-extrapolated central differences."""
    R0 = rotation_matrix(np.radians(pose[3:]))

    def state(x: np.ndarray) -> tuple[np.ndarray, float]:
        R = Rotation.from_rotvec(x[3:]).as_matrix() @ R0
        t = pose[:3] + x[:3]
        return np.linalg.norm(A_TRUE @ R.T + t - B_TRUE, axis=1), float((R @ ROBOT.com + t)[2])

    J, grad = np.empty((6, 6)), np.empty(6)
    for k, h in enumerate([1e-2, 1e-2, 1e-2, 1e-5, 1e-5, 1e-5]):
        parts = []
        for step in (h, h / 2):
            dx = np.zeros(6)
            dx[k] = step
            (lp, zp), (lm, zm) = state(dx), state(-dx)
            parts.append(((lp - lm) / (2 * step), (zp - zm) / (2 * step)))
        J[:, k] = (4 * parts[1][0] - parts[0][0]) / 3
        grad[k] = ROBOT.moving_mass_kg * ROBOT.gravity_mps2 * (4 * parts[1][1] - parts[0][1]) / 3
    forces_n, *_ = lstsq(J.T, grad)
    return forces_n / 1000.0


def rig_with(effects: EffectsConfig, seed: int = 0) -> SimulatedRig:
    return SimulatedRig(ROBOT, RigConfig(seed=seed, errors=ERRORS, effects=effects, leg_resolution_mm=0.0))


def test_electric_effects_off_change_nothing() -> None:
    disabled = EffectsConfig(
        motor_encoder=MotorEncoderConfig(lead_ratio=1.1, pitch_error_mm=0.01),
        drive_compliance=DriveComplianceConfig(c_per_length_mm_per_kn_m=500.0),
    )
    plain, off = rig_with(EffectsConfig()), rig_with(disabled)
    for pose in workspace_poses(3, 1):
        for rig in (plain, off):
            rig.move_to_lengths(rig.controller_ik(pose))
            rig.start_session()
        np.testing.assert_array_equal(off.true_pose(), plain.true_pose())
        assert off.length_corrections_mm() == {}


def test_motor_encoder_scales_the_travel_from_the_home_switch() -> None:
    """True length = l0 + s_home + r (reported - l0 - s_home) + dl0: a straight line in the reported stroke."""
    s_home = np.array([0.0, 5.0, 0.0, 10.0, 0.0, 2.5])
    encoder = MotorEncoderConfig(
        enabled=True, lead_ratio=RATIO.tolist(), home_stroke_mm=s_home.tolist(), homing_repeatability_mm=0.0
    )
    rig = rig_with(EffectsConfig(motor_encoder=encoder))
    reported, true = [], []
    for pose in workspace_poses(8, 2):
        rig.move_to_lengths(rig.controller_ik(pose))
        reported.append(rig.reported_lengths())
        true.append(leg_lengths(rig.true_pose()))
        expected = ROBOT.l0 + s_home + RATIO * (reported[-1] - ROBOT.l0 - s_home) + DL0
        assert np.max(np.abs(true[-1] - expected)) < 1e-8
    # The diagnosis' sensor_scale convention: geometric length = reported + dl0 - g stroke, so g = 1 - r.
    stroke = np.array(reported) - ROBOT.l0
    for i in range(6):
        slope = np.polyfit(stroke[:, i], np.array(true)[:, i] - np.array(reported)[:, i], 1)[0]
        assert -slope == pytest.approx(1.0 - RATIO[i], abs=1e-9)


def test_homing_moves_each_legs_zero_once_per_session_and_is_seeded() -> None:
    sigma = 0.004
    draws = np.array([homing_offsets_mm(7, session, sigma) for session in range(2000)])
    assert np.std(draws) == pytest.approx(sigma, rel=0.05) and abs(np.mean(draws)) < 4 * sigma / np.sqrt(draws.size)
    encoder = MotorEncoderConfig(enabled=True, lead_ratio=RATIO.tolist(), homing_repeatability_mm=sigma)
    rig, twin = (rig_with(EffectsConfig(motor_encoder=encoder), seed=7) for _ in range(2))
    reported = rig.controller_ik(workspace_poses(1, 3)[0])
    rigid = ROBOT.l0 + RATIO * (reported - ROBOT.l0) + DL0
    for session in range(4):
        if session:
            rig.start_session()
            twin.start_session()
        assert rig.session == session
        rig.move_to_lengths(reported)
        twin.move_to_lengths(reported)
        # Whatever the lead ratio, the trip point of this session's switch shifts the whole leg.
        np.testing.assert_allclose(leg_lengths(rig.true_pose()) - rigid, draws[session], rtol=0, atol=1e-9)
        np.testing.assert_array_equal(twin.true_pose(), rig.true_pose())
    assert np.all(np.abs(np.diff(draws[:4], axis=0)) > 1e-7)
    assert np.max(np.abs(homing_offsets_mm(8, 0, sigma) - draws[0])) > 1e-4


def test_pitch_error_repeats_with_every_screw_revolution() -> None:
    amplitude, lead, phase = 0.003, 2.0, np.array([0.0, 30.0, 60.0, 90.0, 120.0, 150.0])
    encoder = MotorEncoderConfig(
        enabled=True, lead_mm=lead, homing_repeatability_mm=0.0, pitch_error_mm=amplitude,
        pitch_phase_deg=phase.tolist(),
    )
    rig = rig_with(EffectsConfig(motor_encoder=encoder))
    base = rig.controller_ik(workspace_poses(1, 4)[0])
    for offset in (0.0, 0.25, 0.5, 1.3, 2.0):
        reported = base + offset
        rig.move_to_lengths(reported)
        stroke = reported - ROBOT.l0
        expected = reported + DL0 + amplitude * np.sin(2 * math.pi * stroke / lead + np.radians(phase))
        assert np.max(np.abs(leg_lengths(rig.true_pose()) - expected)) < 1e-9


def test_drive_compliance_grows_with_the_free_screw_length_under_the_statics_load() -> None:
    c_fixed, c_length, free = 0.05, np.array([300.0, 400.0, 350.0, 250.0, 450.0, 500.0]), 20.0
    effects = EffectsConfig(
        motor_encoder=MotorEncoderConfig(enabled=True, lead_ratio=RATIO.tolist(), homing_repeatability_mm=0.0),
        drive_compliance=DriveComplianceConfig(
            enabled=True, c_fixed_mm_per_kn=c_fixed, c_per_length_mm_per_kn_m=c_length.tolist(),
            free_length_at_zero_stroke_mm=free,
        ),
    )
    rig = rig_with(effects)
    sags = []
    for pose in workspace_poses(6, 5):
        reported = rig.controller_ik(pose)
        rig.move_to_lengths(reported)
        true = rig.true_pose()
        true_stroke = RATIO * (reported - ROBOT.l0)
        F = forces_by_virtual_work_kn(true)
        sag = -(c_fixed + c_length * (free + true_stroke) / 1000.0) * F
        assert np.max(np.abs(leg_lengths(true) - (reported + DL0 + (true_stroke - (reported - ROBOT.l0)) + sag))) < 1e-8
        assert np.all(F > 0)
        sags.append(sag)
    assert np.max(np.abs(sags)) > 0.1 * 0.001  # a visible effect at these (large) compliances


def test_default_drive_compliance_is_a_steel_ball_screw_and_negligible_on_a_light_platform() -> None:
    root_area_mm2 = math.pi / 4 * 9.5**2
    assert BALL_SCREW_C_PER_LENGTH_MM_PER_KN_M == pytest.approx(1e6 / (root_area_mm2 * 2.1e5), rel=1e-12)
    rig = rig_with(EffectsConfig(drive_compliance=DriveComplianceConfig(enabled=True)))
    sags, compliances = [], []
    for lengths in (np.full(6, ROBOT.leg_limits[0] + 1.0), np.full(6, ROBOT.leg_limits[1] - 1.0)):
        rig.move_to_lengths(lengths)
        sags.append(rig.length_corrections_mm()["drive_compliance"])
        compliances.append(-sags[-1] / forces_by_virtual_work_kn(rig.true_pose()))
    # A few newtons per leg: a sag below 0.2 µm; over 48 mm of stroke the compliance grows by 48 mm / (A E).
    assert np.all(np.array(sags) < 0) and np.max(np.abs(sags)) < 2e-4
    np.testing.assert_allclose(compliances[1] - compliances[0], 0.048 * BALL_SCREW_C_PER_LENGTH_MM_PER_KN_M, rtol=1e-6)
    assert drive_compliance_for_signature(0.04, 0.007, 50.0) == pytest.approx(0.04 / (0.007 * 0.05))


def test_electric_config_validation() -> None:
    with pytest.raises(ValidationError):
        MotorEncoderConfig(lead_ratio=0.0)
    with pytest.raises(ValidationError):
        MotorEncoderConfig(lead_mm=[2.0, 2.0, 2.0, 2.0, 2.0, -2.0])
    with pytest.raises(ValidationError):
        MotorEncoderConfig(homing_repeatability_mm=-0.001)
    with pytest.raises(ValidationError):
        DriveComplianceConfig(c_per_length_mm_per_kn_m=-1.0)
    with pytest.raises(ValidationError):
        EffectsConfig.model_validate({"motor_encoder": {"enabled": True, "lead_ratoi": 1.0}})
    on = EffectsConfig(
        motor_encoder=MotorEncoderConfig(enabled=True), drive_compliance=DriveComplianceConfig(enabled=True)
    )
    assert on.active() == ("motor_encoder", "drive_compliance")


def test_measure_rows_from_several_sessions_home_the_legs_again() -> None:
    """measure_session_starts: every new session waits, powers on (homes) and makes an unrecorded excursion."""
    sigma = 0.004
    options = RecordingOptions(
        session_gap_s=3600.0 * 20, measure_session_starts=(3, 6), include_cmd=False, include_temp=False
    )
    t_verify = second_session_start_s(9, seconds_per_pose=60.0, options=options)
    assert t_verify == 9 * 60.0 + 3 * (72000.0 + 2 * 60.0) - 2 * 60.0
    encoder = MotorEncoderConfig(enabled=True, lead_ratio=RATIO.tolist(), homing_repeatability_mm=sigma)
    config = RigConfig(seed=11, errors=ERRORS, effects=EffectsConfig(motor_encoder=encoder), leg_resolution_mm=0.0)
    rec, truth = simulate_with_truth(
        ROBOT, config, workspace_poses(9, 12), workspace_poses(2, 13), seconds_per_pose=60.0, options=options
    )
    assert np.flatnonzero(np.diff(rec.time_s) > 3600.0).tolist() == [2, 5, 8]
    assert rec.time_s[9] == t_verify + 3 * 60.0  # power-on, excursion out and home, then the first verify move
    sessions = [0, 0, 0, 1, 1, 1, 2, 2, 2, 3, 3]
    for k, session in enumerate(sessions):
        expected = ROBOT.l0 + RATIO * (rec.legs_mm[k] - ROBOT.l0) + DL0 + homing_offsets_mm(11, session, sigma)
        np.testing.assert_allclose(leg_lengths(truth[k]), expected, rtol=0, atol=1e-8)
    for bad in ((0, 3), (3, 3), (5, 3)):
        with pytest.raises(ValueError, match="measure_session_starts"):
            RecordingOptions(session_gap_s=1.0, measure_session_starts=bad)
    with pytest.raises(ValueError, match="measure_session_starts"):
        RecordingOptions(measure_session_starts=(3,))
    with pytest.raises(ValueError, match="measure_session_starts"):
        simulate_with_truth(ROBOT, config, workspace_poses(3, 12), workspace_poses(1, 13), options=options)


# ---------------------------------------------------------------- the committed example


def _generator() -> ModuleType:
    spec = importlib.util.spec_from_file_location("electric_hexapod_make_recording", EXAMPLE / "make_recording.py")
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module
    spec.loader.exec_module(module)
    return module


@pytest.fixture(scope="module")
def generated() -> tuple[ModuleType, tuple]:
    module = _generator()
    return module, module.simulate()


@pytest.fixture(scope="module")
def signature(generated) -> dict[str, np.ndarray]:
    module, (robot, config, rec, _) = generated
    return module.drive_signature(robot, config, rec)


def test_committed_csv_is_what_the_generator_produces(generated, tmp_path) -> None:
    _, (_, _, rec, _) = generated
    fresh = tmp_path / "recording.csv"
    write_recording(fresh, rec)
    assert (EXAMPLE / "recording.csv").read_text() == fresh.read_text()


def test_recording_looks_like_a_real_loggers_three_sessions() -> None:
    robot = load_robot(EXAMPLE / "robot.toml")
    assert (robot.actuator_kind, robot.transducer) == ("electric", "motor_encoder")
    assert 2.0 <= robot.moving_mass_kg <= 6.0
    rec = read_recording(EXAMPLE / "recording.csv", robot)
    measure, verify = rec.phase == "measure", rec.phase == "verify"
    assert (int(measure.sum()), int(verify.sum())) == (108, 60) and np.all(measure[:108])
    assert not rec.has_cmd and rec.temp_c is None and list(rec.extra) == ["sphere_fit_rms_mm"]
    gaps_h = np.diff(rec.time_s) / 3600.0
    assert np.flatnonzero(gaps_h > 4.0).tolist() == [53, 107]
    assert np.all(gaps_h > 0)
    assert len(np.unique(np.round(rec.legs_mm, 1), axis=0)) == rec.n  # no repeated poses
    rms = rec.extra["sphere_fit_rms_mm"]
    assert 0.0005 < np.median(rms) < 0.003


def test_example_truth_is_a_six_percent_fault_with_a_near_alias_drive(generated, signature) -> None:
    module, (robot, config, rec, _) = generated
    ratio = np.asarray(config.effects.motor_encoder.lead_ratio)
    faulty = np.flatnonzero(np.abs(ratio - 1.0) > 0.01)
    assert faulty.tolist() == [module.fault_leg()] and 0.04 < 1.0 - ratio[faulty[0]] < 0.08
    assert np.all(np.abs(signature["alias_cos"]) > 0.7)
    assert np.all(signature["spread_mm"] > 0.01)
    # The faulty leg's length error over its recorded stroke, as the rig made it: millimetres.
    stroke = rec.legs_mm[:, faulty[0]] - robot.l0[faulty[0]]
    assert (1.0 - ratio[faulty[0]]) * np.ptp(stroke) > 2.0


def test_readme_states_the_generated_truth(generated, signature) -> None:
    module, simulated = generated
    readme = (EXAMPLE / "README.md").read_text()
    assert "simulated" in readme.lower()
    assert module.truth_markdown(simulated, signature) in readme
