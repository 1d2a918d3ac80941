"""The rig's out-of-library and session effects and the recording options, checked against values worked out here.

Leg lengths at a pose are recomputed with hilcal.robot.rotation_matrix (not the rig's scipy rotations; helpers
shared with test_sim_physics); the Hooke-joint offset is checked against the closed form
|p - b|² = d² + L² + 2 d L cos θ2, sin θ2 = (p - b)·e1 / L, solved here by a scalar root search, instead of the
rig's fixed-point iteration.
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy.optimize import brentq
from scipy.spatial.transform import Rotation

from hilcal.planning.design import verification_poses
from hilcal.recording import read_recording, write_recording
from hilcal.robot import rotation_matrix
from procedures.cli.simulated_recording import RecordingOptions, second_session_start_s, simulate_with_truth
from sim_devices.rig import unlisted_physics
from sim_devices.rig.config import (
    EffectsConfig,
    JointBacklashConfig,
    LegComplianceConfig,
    RigConfig,
    SensorScaleConfig,
    TemperatureConfig,
)
from sim_devices.rig.rig import SimulatedRig
from sim_devices.rig.unlisted_concealed import (
    CONCEALABLE_EFFECT_NAMES,
    UNLISTED_EFFECT_NAMES,
    concealed_unlisted_config,
)
from sim_devices.rig.unlisted_config import (
    CyclicStrokeErrorConfig,
    FrictionHysteresisConfig,
    HookeJointOffsetConfig,
    LocalHeatingConfig,
    TransducerBowConfig,
    ZeroShiftConfig,
)
from tests.sim_devices.test_sim_physics import (
    A_TRUE,
    B_TRUE,
    DL0,
    ERRORS,
    ROBOT,
    forces_by_virtual_work_kn,
    leg_lengths,
    workspace_poses,
)

L0 = 3800.0
STROKE_MM = 1000.0
"""The default robot: l0 = 3800 mm, leg limits 3800-4800 mm, so strokes run from 0 to 1000 mm."""
NO_DRIFT = TemperatureConfig(t0_c=20.0, drift_k_per_h=0.0, amplitude_k=0.0, sensor_noise_k=0.0)


def joints(pose: np.ndarray) -> np.ndarray:
    """(6, 3) true platform joints at a pose (hilcal's rotation matrix)."""
    return A_TRUE @ rotation_matrix(np.radians(pose[3:])).T + pose[:3]


def rig_with(effects: EffectsConfig, **kwargs: object) -> SimulatedRig:
    kwargs.setdefault("temperature", NO_DRIFT)
    return SimulatedRig(ROBOT, RigConfig(errors=ERRORS, effects=effects, **kwargs))


def horizontal_first_axes() -> np.ndarray:
    """e1 = unit(z × u_home): horizontal and perpendicular to each leg at the home pose."""
    u = joints(ROBOT.home) - B_TRUE
    e1 = np.cross([0.0, 0.0, 1.0], u)
    return e1 / np.linalg.norm(e1, axis=1, keepdims=True)


def hooke_dl_closed_form(p: np.ndarray, e1: np.ndarray, d: np.ndarray) -> np.ndarray:
    """Δl = |P| - L with P = p - b: |P|² = d² + L² + 2 d sqrt(L² - (P·e1)²), solved for L per leg."""
    out = np.empty(6)
    for i in range(6):
        P = p[i] - B_TRUE[i]
        norm, along = np.linalg.norm(P), P @ e1[i]

        def f(L: float, norm: float = norm, along: float = along, di: float = d[i]) -> float:
            return di**2 + L**2 + 2 * di * np.sqrt(L**2 - along**2) - norm**2

        L = brentq(f, abs(along) + 1e-9, norm + abs(d[i]) + 1.0, xtol=1e-13, rtol=1e-15)
        out[i] = norm - L
    return out


# ---------------------------------------------------------------- each effect at hand-computed states


def test_transducer_bow_is_a_half_sine_over_the_stroke_range() -> None:
    amplitude = np.array([0.2, 0.0, 0.0, -0.1, 0.0, 0.05])
    lo, hi = np.zeros(6), np.full(6, STROKE_MM)
    for stroke, factor in ((0.0, 0.0), (1000.0, 0.0), (500.0, 1.0), (250.0, np.sqrt(0.5)), (750.0, np.sqrt(0.5))):
        got = unlisted_physics.transducer_bow_mm(amplitude, np.full(6, stroke), lo, hi)
        np.testing.assert_allclose(got, amplitude * factor, atol=1e-15)
    rig = rig_with(EffectsConfig(transducer_bow=TransducerBowConfig(enabled=True, amplitude_mm=amplitude.tolist())))
    for pose in workspace_poses(4, 1):
        reported = rig.controller_ik(pose)
        rig.move_to_lengths(reported)
        bow = amplitude * np.sin(np.pi * (reported - L0) / STROKE_MM)
        assert np.max(np.abs(leg_lengths(rig.true_pose()) - (reported + DL0 + bow))) < 1e-9


def test_cyclic_stroke_error_repeats_every_period() -> None:
    cfg = CyclicStrokeErrorConfig(enabled=True, amplitude_mm=0.03, period_mm=20.0, phase_deg=90.0)
    for stroke, value in ((0.0, 0.03), (5.0, 0.0), (10.0, -0.03), (20.0, 0.03), (415.0, 0.0), (430.0, -0.03)):
        got = unlisted_physics.cyclic_stroke_error_mm(np.full(6, 0.03), np.full(6, 20.0), np.full(6, 90.0),
                                                      np.full(6, stroke))
        np.testing.assert_allclose(got, value, atol=1e-15)
    rig = rig_with(EffectsConfig(cyclic_stroke_error=cfg))
    for pose in workspace_poses(4, 2):
        reported = rig.controller_ik(pose)
        rig.move_to_lengths(reported)
        cyclic = 0.03 * np.cos(2 * np.pi * (reported - L0) / 20.0)
        assert np.max(np.abs(leg_lengths(rig.true_pose()) - (reported + DL0 + cyclic))) < 1e-9


def test_hooke_offset_matches_the_joint_angle_construction() -> None:
    """Build p from the joint angles (c = b + d n, p = c + L u) and compare with the closed form."""
    e1 = horizontal_first_axes()
    n0 = np.cross(e1, np.cross(joints(ROBOT.home) - B_TRUE, e1))
    n0 /= np.linalg.norm(n0, axis=1, keepdims=True)
    e2 = np.cross(n0, e1)
    d = np.array([1.5, -2.0, 40.0, 0.0, 10.0, 60.0])
    rng = np.random.default_rng(3)
    for _ in range(5):
        theta1, theta2, L = rng.uniform(-0.3, 0.3, 6), rng.uniform(-0.3, 0.3, 6), rng.uniform(3800, 4800, 6)
        p = np.empty((6, 3))
        for i in range(6):
            R1 = Rotation.from_rotvec(e1[i] * theta1[i])
            u = (R1 * Rotation.from_rotvec(e2[i] * theta2[i])).apply(n0[i])
            p[i] = B_TRUE[i] + d[i] * R1.apply(n0[i]) + L[i] * u
        got = unlisted_physics.hooke_offset_mm(d, e1, B_TRUE, p)
        np.testing.assert_allclose(got, np.sqrt(d**2 + L**2 + 2 * d * L * np.cos(theta2)) - L, atol=1e-10)
    straight = B_TRUE + 4300.0 * n0
    np.testing.assert_allclose(unlisted_physics.hooke_offset_mm(d, e1, B_TRUE, straight), d, atol=1e-10)


def test_hooke_offset_in_the_rig_is_self_consistent() -> None:
    d = np.array([30.0, 45.0, -20.0, 50.0, 0.0, 35.0])
    rig = rig_with(EffectsConfig(hooke_joint_offset=HookeJointOffsetConfig(enabled=True, offset_mm=d.tolist())))
    e1 = horizontal_first_axes()
    signature = []
    for pose in workspace_poses(5, 4):
        reported = rig.controller_ik(pose)
        rig.move_to_lengths(reported)
        true = rig.true_pose()
        expected = hooke_dl_closed_form(joints(true), e1, d)
        assert np.max(np.abs(leg_lengths(true) - (reported + DL0 + expected))) < 1e-8
        signature.append(expected - d)
    assert np.ptp(np.array(signature), axis=0)[[0, 1, 3]].min() > 0.01


def test_hooke_offset_left_over_by_rigid_joint_errors_is_as_documented() -> None:
    """The documented fraction (sim_devices.rig.unlisted_physics): 0.52-0.84 per leg, median 0.68, on these poses."""
    poses = verification_poses(ROBOT, 56, 0)
    rig = rig_with(EffectsConfig(hooke_joint_offset=HookeJointOffsetConfig(enabled=True, offset_mm=1.5)),
                   cmm_noise_mm=0.0)
    dl, u, rtu = [], [], []
    for pose in poses:
        rig.move_to_lengths(rig.controller_ik(pose))
        true = rig.true_pose()
        legs = joints(true) - B_TRUE
        unit = legs / np.linalg.norm(legs, axis=1, keepdims=True)
        dl.append(leg_lengths(true) - rig.reported_lengths() - DL0)
        u.append(unit)
        rtu.append(unit @ rotation_matrix(np.radians(true[3:])))
    dl_arr, u_arr, rtu_arr = np.array(dl), np.array(u), np.array(rtu)
    fraction = np.empty(6)
    for i in range(6):
        X = np.column_stack([np.ones(len(poses)), u_arr[:, i], rtu_arr[:, i]])
        y = dl_arr[:, i] - dl_arr[:, i].mean()
        resid = y - X @ np.linalg.lstsq(X, y, rcond=None)[0]
        fraction[i] = resid @ resid / (y @ y)
    assert fraction.min() == pytest.approx(0.52, abs=0.01)
    assert fraction.max() == pytest.approx(0.84, abs=0.01)
    assert np.median(fraction) == pytest.approx(0.68, abs=0.01)


def test_local_heating_grows_after_each_power_on_and_the_ambient_sensor_misses_it() -> None:
    heating = LocalHeatingConfig(enabled=True, delta_t_k=[0.0, 5.0, 0.0, 0.0, 0.0, 0.0], time_constant_s=1000.0,
                                 alpha_ppm_per_k=12.0)
    rig = rig_with(EffectsConfig(local_heating=heating))
    reported = rig.controller_ik(workspace_poses(1, 5)[0])
    rig.move_to_lengths(reported)
    for clock, since_power_on in ((1000.0, 1000.0), (3000.0, 3000.0)):
        rig.set_time(clock)
        L = leg_lengths(rig.true_pose())
        excess_k = 5.0 * (1.0 - np.exp(-since_power_on / 1000.0))
        np.testing.assert_allclose(L - (reported + DL0), [0, 12e-6 * L[1] * excess_k, 0, 0, 0, 0], atol=1e-9)
        assert rig.temperature_c() == 20.0
    rig.set_time(90000.0)
    rig.start_session()
    np.testing.assert_allclose(leg_lengths(rig.true_pose()), reported + DL0, atol=1e-9)
    rig.advance_time(500.0)
    L = leg_lengths(rig.true_pose())
    assert L[1] - (reported[1] + DL0[1]) == pytest.approx(12e-6 * L[1] * 5.0 * (1 - np.exp(-0.5)), abs=1e-9)


def test_friction_hysteresis_follows_the_direction_and_size_of_the_last_move() -> None:
    h = np.array([0.02, 0.04, 0.03, 0.05, 0.01, 0.06])
    cfg = FrictionHysteresisConfig(enabled=True, amplitude_mm=h.tolist(), length_mm=5.0)
    rig = rig_with(EffectsConfig(friction_hysteresis=cfg), leg_resolution_mm=0.0)
    start = rig.reported_lengths()
    np.testing.assert_allclose(leg_lengths(rig.true_pose()), start + DL0 + h, atol=1e-9)  # saturated at the start
    moves = [
        np.array([10.0, -10.0, 5.0, -5.0, 1.0, -1.0]),
        np.array([10.0, -10.0, 5.0, -5.0, 1.0, -1.0]) + 0.0005,  # below the 1 µm deadband: state kept
        np.array([8.0, -7.0, 5.0, -5.0, 3.0, -1.0]),
    ]
    wanted = [
        h * np.array([1, -1, 1, -1, 1, -1]) * (1 - np.exp(-np.array([10.0, 10, 5, 5, 1, 1]) / 5.0)),
        h * np.array([1, -1, 1, -1, 1, -1]) * (1 - np.exp(-np.array([10.0, 10, 5, 5, 1, 1]) / 5.0)),
        h * np.array([-1, 1, 1, -1, 1, -1]) * (1 - np.exp(-np.array([2.0005, 2.9995, 5, 5, 1.9995, 1]) / 5.0)),
    ]
    for offset, want in zip(moves, wanted, strict=True):
        rig.move_to_lengths(start + offset)
        np.testing.assert_allclose(leg_lengths(rig.true_pose()) - (start + offset + DL0), want, atol=1e-9)


def test_zero_shift_applies_from_its_time_on() -> None:
    shift = [0.004, 0.0, -0.003, 0.0, 0.0, 0.0]
    rig = rig_with(EffectsConfig(zero_shift=ZeroShiftConfig(enabled=True, shift_mm=shift, from_time_s=1000.0)))
    reported = rig.controller_ik(workspace_poses(1, 6)[0])
    rig.move_to_lengths(reported)
    rig.set_time(999.0)
    np.testing.assert_allclose(leg_lengths(rig.true_pose()), reported + DL0, atol=1e-9)
    rig.set_time(1000.0)
    np.testing.assert_allclose(leg_lengths(rig.true_pose()), reported + DL0 + shift, atol=1e-9)


# ---------------------------------------------------------------- off by default, combinations


def test_disabled_effects_change_nothing() -> None:
    configured = EffectsConfig(
        transducer_bow=TransducerBowConfig(amplitude_mm=1.0),
        cyclic_stroke_error=CyclicStrokeErrorConfig(amplitude_mm=1.0),
        hooke_joint_offset=HookeJointOffsetConfig(offset_mm=50.0),
        local_heating=LocalHeatingConfig(delta_t_k=20.0),
        friction_hysteresis=FrictionHysteresisConfig(amplitude_mm=1.0),
        zero_shift=ZeroShiftConfig(shift_mm=1.0),
    )
    assert EffectsConfig().active() == configured.active() == ()
    plain, rig = rig_with(EffectsConfig()), rig_with(configured)
    for pose in workspace_poses(3, 7):
        for r in (plain, rig):
            r.advance_time(600.0)
            r.move_to_lengths(r.controller_ik(pose))
        np.testing.assert_array_equal(rig.true_pose(), plain.true_pose())
        assert rig.length_corrections_mm() == {}


def test_out_of_library_effects_combine_with_library_effects() -> None:
    c, g_ppm = 0.1, np.array([300.0, -200.0, 100.0, 50.0, -400.0, 250.0])
    bow, d = np.array([0.1, 0.0, -0.2, 0.0, 0.15, 0.0]), np.full(6, 25.0)
    heating_k = np.array([0.0, 0.0, 0.0, 4.0, 0.0, 0.0])
    effects = EffectsConfig(
        leg_compliance=LegComplianceConfig(enabled=True, c_mm_per_kn=c),
        sensor_scale=SensorScaleConfig(enabled=True, gain_error_ppm=g_ppm.tolist()),
        joint_backlash=JointBacklashConfig(enabled=True, backlash_mm=0.04),
        transducer_bow=TransducerBowConfig(enabled=True, amplitude_mm=bow.tolist()),
        cyclic_stroke_error=CyclicStrokeErrorConfig(enabled=True, amplitude_mm=0.02, period_mm=40.0),
        hooke_joint_offset=HookeJointOffsetConfig(enabled=True, offset_mm=d.tolist()),
        local_heating=LocalHeatingConfig(enabled=True, delta_t_k=heating_k.tolist(), time_constant_s=600.0),
        zero_shift=ZeroShiftConfig(enabled=True, shift_mm=0.005, from_time_s=0.0),
    )
    rig = rig_with(effects)
    e1 = horizontal_first_axes()
    for pose in workspace_poses(4, 8):
        rig.advance_time(300.0)
        reported = rig.controller_ik(pose)
        rig.move_to_lengths(reported)
        true = rig.true_pose()
        L, F = leg_lengths(true), forces_by_virtual_work_kn(true)
        stroke = (reported - L0) / (1 + g_ppm * 1e-6)
        expected = (
            L0 + stroke + DL0 - c * F + rig.motion_direction() * 0.02
            + bow * np.sin(np.pi * stroke / STROKE_MM)
            + 0.02 * np.sin(2 * np.pi * stroke / 40.0)
            + hooke_dl_closed_form(joints(true), e1, d)
            + 11.5e-6 * L * heating_k * (1 - np.exp(-rig.time_s / 600.0))
            + 0.005
        )
        assert np.max(np.abs(L - expected)) < 1e-8
        parts = rig.length_corrections_mm()
        assert len(parts) == 8
        np.testing.assert_allclose(sum(parts.values()), L - reported - DL0, atol=1e-8)


# ---------------------------------------------------------------- concealed configurations


def test_concealed_unlisted_configs_are_seeded_single_effects() -> None:
    assert UNLISTED_EFFECT_NAMES == ("transducer_bow", "cyclic_stroke_error", "hooke_joint_offset", "local_heating")
    assert CONCEALABLE_EFFECT_NAMES == (*UNLISTED_EFFECT_NAMES, "friction_hysteresis")
    for name in CONCEALABLE_EFFECT_NAMES:
        effects = concealed_unlisted_config(name, 1.0, seed=3)
        assert effects.active() == (name,)
        assert effects == concealed_unlisted_config(name, 1.0, 3) != concealed_unlisted_config(name, 1.0, 4)
        zero = concealed_unlisted_config(name, 0.0, seed=3)
        rig = rig_with(zero)
        rig.advance_time(3000.0)
        reported = rig.controller_ik(workspace_poses(1, 9)[0])
        rig.move_to_lengths(reported)
        assert np.max(np.abs(rig.length_corrections_mm()[name])) < 1e-12
    bow = np.array(concealed_unlisted_config("transducer_bow", 1.0, 0).transducer_bow.amplitude_mm)
    assert np.count_nonzero(bow) == 3 and np.all((np.abs(bow[bow != 0]) >= 0.18) & (np.abs(bow[bow != 0]) <= 0.32))
    heating = np.array(concealed_unlisted_config("local_heating", 2.0, 0).local_heating.delta_t_k)
    assert np.count_nonzero(heating) == 1 and 12.0 <= heating.max() <= 20.0
    assert concealed_unlisted_config("none", 1.0, 0) == EffectsConfig()
    with pytest.raises(ValueError, match="unknown effect"):
        concealed_unlisted_config("leg_compliance", 1.0, 0)
    with pytest.raises(ValueError, match="magnitude_scale"):
        concealed_unlisted_config("transducer_bow", -1.0, 0)


def test_config_validation() -> None:
    with pytest.raises(ValueError):
        CyclicStrokeErrorConfig(period_mm=0.0)
    with pytest.raises(ValueError):
        FrictionHysteresisConfig(amplitude_mm=-0.01)
    with pytest.raises(ValueError):
        LocalHeatingConfig(time_constant_s=0.0)
    with pytest.raises(ValueError):
        TransducerBowConfig(amplitude_mm=[0.1] * 5)
    with pytest.raises(ValueError):
        ZeroShiftConfig(from_time_s=-1.0)


# ---------------------------------------------------------------- recording options: sessions and columns


def test_two_sessions_without_cmd_and_temperature(tmp_path) -> None:
    measure, verify = workspace_poses(9, 10), workspace_poses(4, 11)
    options = RecordingOptions(session_gap_s=86400.0, include_cmd=False, include_temp=False)
    t2 = second_session_start_s(9, seconds_per_pose=60.0, options=options)
    assert t2 == 9 * 60.0 + 86400.0
    shift = [0.0, 0.05, 0.0, 0.0, -0.04, 0.0]
    config = RigConfig(seed=1, errors=ERRORS, effects=EffectsConfig(
        zero_shift=ZeroShiftConfig(enabled=True, shift_mm=shift, from_time_s=t2)))
    rec, truth = simulate_with_truth(ROBOT, config, measure, verify, seconds_per_pose=60.0, options=options)
    # Verify rows follow the power-on, an unrecorded excursion (two moves) and their own move.
    np.testing.assert_allclose(rec.time_s[:9], 60.0 * np.arange(1, 10))
    np.testing.assert_allclose(rec.time_s[9:], t2 + 60.0 * (2 + np.arange(1, 5)))
    assert not rec.has_cmd and rec.temp_c is None and set(rec.extra) == {"sphere_fit_rms_mm"}
    plain, _ = simulate_with_truth(ROBOT, RigConfig(seed=1, errors=ERRORS), measure, verify, seconds_per_pose=60.0)
    np.testing.assert_array_equal(rec.legs_mm, plain.legs_mm)
    for k in range(13):
        L = leg_lengths(truth[k])
        np.testing.assert_allclose(L - rec.legs_mm[k] - DL0, shift if k >= 9 else 0.0, atol=1e-8)
    path = tmp_path / "rec.csv"
    write_recording(path, rec)
    header = path.read_text().splitlines()[0].split(",")
    assert "temp_c" not in header and header[-1] == "sphere_fit_rms_mm"
    assert path.read_text().splitlines()[1].split(",")[3:9] == [""] * 6
    back = read_recording(path, ROBOT)
    np.testing.assert_array_equal(back.meas, rec.meas)
    assert not back.has_cmd


def test_unknown_start_and_optional_columns() -> None:
    measure, verify = workspace_poses(9, 12), workspace_poses(2, 13)
    measure[0] = ROBOT.home  # the legs do not move for the first row: the state from before the recording shows
    backlash = EffectsConfig(joint_backlash=JointBacklashConfig(enabled=True, backlash_mm=0.5))
    config = RigConfig(seed=4, errors=ERRORS, effects=backlash)
    known, known_truth = simulate_with_truth(ROBOT, config, measure, verify)
    unknown, unknown_truth = simulate_with_truth(
        ROBOT, config, measure, verify, options=RecordingOptions(unknown_start=True, include_sphere_fit_rms=False)
    )
    np.testing.assert_allclose(unknown.time_s, known.time_s + 90.0)
    assert set(unknown.extra) == {"temp_c"} and unknown.has_cmd
    # A fresh rig remembers "extended" on every leg; after the excursion some legs last retracted to reach home,
    # so the first true pose differs by the backlash on those legs. The next move sets every leg's direction.
    first = leg_lengths(unknown_truth[0]) - leg_lengths(known_truth[0])
    retracted = np.isclose(first, -0.5, atol=1e-8)
    assert np.all(retracted | np.isclose(first, 0.0, atol=1e-8)) and 0 < np.count_nonzero(retracted) < 6
    np.testing.assert_allclose(leg_lengths(unknown_truth[1]), leg_lengths(known_truth[1]), atol=1e-8)
    # Ending the excursion at its random pose instead: one move fewer, and the first row is then reached from that
    # pose, i.e. from the same side as the excursion's way home.
    options = RecordingOptions(unknown_start=True, excursion_end="random")
    assert second_session_start_s(9, seconds_per_pose=45.0, options=RecordingOptions(
        session_gap_s=0.0, unknown_start=True, excursion_end="random")) == 45.0 + 9 * 45.0
    elsewhere, elsewhere_truth = simulate_with_truth(ROBOT, config, measure, verify, options=options)
    np.testing.assert_allclose(elsewhere.time_s, known.time_s + 45.0)
    np.testing.assert_allclose(elsewhere_truth, unknown_truth, atol=1e-9)
    with pytest.raises(ValueError, match="excursion_end"):
        RecordingOptions(excursion_end="park")  # type: ignore[arg-type]


def test_a_day_gap_with_a_drifting_temperature_is_refused() -> None:
    config = RigConfig(seed=1, errors=ERRORS)
    assert config.temperature.drift_k_per_h > 0
    with pytest.raises(ValueError, match="drift_k_per_h"):
        simulate_with_truth(ROBOT, config, workspace_poses(9, 14), workspace_poses(2, 15),
                            options=RecordingOptions(session_gap_s=86400.0))
    with pytest.raises(ValueError, match="session_gap_s"):
        RecordingOptions(session_gap_s=-1.0)
