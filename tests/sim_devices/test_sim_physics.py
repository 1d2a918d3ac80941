"""The rig's non-geometric truth physics, checked against independent computations made here.

Leg loads are recomputed by virtual work (numerical Jacobian of the leg lengths and of the height of the
centre of mass, solved with scipy's least squares) instead of the rig's 6x6 equilibrium; leg lengths at a
pose are recomputed with hilcal.robot.rotation_matrix instead of the rig's scipy rotations.
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy.linalg import lstsq
from scipy.spatial.transform import Rotation
from scipy.stats import kurtosis

from hilcal.robot import default_robot, rotation_matrix
from procedures.cli.simulated_recording import simulate_recording
from sim_devices.rig.config import (
    EFFECT_NAMES,
    CmmPose,
    EffectsConfig,
    JointBacklashConfig,
    LegComplianceConfig,
    OilColumnComplianceConfig,
    RigConfig,
    SensorScaleConfig,
    TemperatureConfig,
    ThermalExpansionConfig,
    concealed_effect_config,
    load_errors,
)
from sim_devices.rig.rig import SimulatedRig

ROBOT = default_robot()
ERRORS = load_errors("table2")
DA, DB, DL0 = ERRORS.as_arrays()
A_TRUE, B_TRUE = ROBOT.a + DA, ROBOT.b + DB
FIXED_35C = TemperatureConfig(t0_c=35.0, drift_k_per_h=0.0, amplitude_k=0.0, sensor_noise_k=0.0)


def workspace_poses(n: int, seed: int) -> np.ndarray:
    """Poses in the central 80 % of the workspace (all leg lengths inside the limits)."""
    lo, hi = ROBOT.workspace.T
    mid, half = (lo + hi) / 2, (hi - lo) / 2 * 0.8
    return np.random.default_rng(seed).uniform(mid - half, mid + half, (n, 6))


def leg_lengths(pose: np.ndarray) -> np.ndarray:
    """|R a_i + t - b_i| of the true geometry."""
    R = rotation_matrix(np.radians(pose[3:]))
    return np.linalg.norm(A_TRUE @ R.T + pose[:3] - B_TRUE, axis=1)


def forces_by_virtual_work_kn(pose: np.ndarray) -> np.ndarray:
    """Axial compressions (kN) from virtual work: J^T F = grad(m g z_com), J = d(leg lengths)/d(t, rotation).

    Derivatives by Richardson-extrapolated central differences (truncation error O(h^4)).
    """
    R0 = rotation_matrix(np.radians(pose[3:]))

    def state(x: np.ndarray) -> tuple[np.ndarray, float]:
        R = Rotation.from_rotvec(x[3:]).as_matrix() @ R0
        t = pose[:3] + x[:3]
        return np.linalg.norm(A_TRUE @ R.T + t - B_TRUE, axis=1), float((R @ ROBOT.com + t)[2])

    def central(k: int, h: float) -> tuple[np.ndarray, float]:
        dx = np.zeros(6)
        dx[k] = h
        (lp, zp), (lm, zm) = state(dx), state(-dx)
        return (lp - lm) / (2 * h), (zp - zm) / (2 * h)

    steps = np.array([1e-1, 1e-1, 1e-1, 1e-5, 1e-5, 1e-5])
    J = np.empty((6, 6))
    grad_potential = np.empty(6)
    for k, h in enumerate(steps):
        (dl_h, dz_h), (dl_half, dz_half) = central(k, h), central(k, h / 2)
        J[:, k] = (4 * dl_half - dl_h) / 3
        grad_potential[k] = ROBOT.moving_mass_kg * ROBOT.gravity_mps2 * (4 * dz_half - dz_h) / 3
    forces_n, *_ = lstsq(J.T, grad_potential)
    return forces_n / 1000.0


def rig_with(effects: EffectsConfig, **kwargs: object) -> SimulatedRig:
    return SimulatedRig(ROBOT, RigConfig(errors=ERRORS, effects=effects, **kwargs))


# ---------------------------------------------------------------- effects off: the rig of before


def test_effects_off_reproduces_the_previous_rig_bit_for_bit() -> None:
    """Pose and first CMM draw pinned from the rig before the physics existed (seed 3, Table 2 errors), to a few ulp
    (the pins were made with scipy's rotations, the rig now has its own)."""
    reported = np.array([4188.606, 4285.532, 4297.242, 4561.263, 4424.968, 4746.241])
    pinned_pose = [76.1647803714708, 237.55384600130245, 3236.489137093545,
                   -4.431933992924967, -3.1834618404202417, 7.499034373818749]
    pinned_platform = [[-1219.359366389033, -1178.7766820909637, 3141.725426924031],
                       [-818.093221188151, -2860.0353083551236, 3030.740061542622],
                       [439.8114455075481, -1669.8520942037546, 3064.736361104315]]
    pinned_base = [[-3084.1644397661144, -759.5169520015124, -82.84060997517754],
                   [-132.36863044707025, -4795.211218220796, -81.12060252068567],
                   [1880.9063534245513, -225.3843888795684, -333.074360926529]]
    disabled_with_magnitudes = EffectsConfig(
        leg_compliance=LegComplianceConfig(c_mm_per_kn=1.0), joint_backlash=JointBacklashConfig(backlash_mm=1.0)
    )
    for effects in (EffectsConfig(), disabled_with_magnitudes):
        rig = SimulatedRig(ROBOT, RigConfig(seed=3, errors=ERRORS, effects=effects))
        rig.advance_time(3600.0)
        rig.move_to_lengths(reported)
        pose = rig.true_pose()
        platform, base = rig.measure_spheres()
        rig.advance_time(7200.0)
        np.testing.assert_array_equal(rig.true_pose(), pose)
        np.testing.assert_allclose(pose, pinned_pose, rtol=1e-15, atol=1e-12)
        np.testing.assert_allclose(platform, pinned_platform, rtol=1e-15, atol=1e-12)
        np.testing.assert_allclose(base, pinned_base, rtol=1e-15, atol=1e-12)
        assert rig.length_corrections_mm() == {}


# ---------------------------------------------------------------- statics and each effect


def test_leg_forces_match_virtual_work_and_carry_the_weight() -> None:
    rig = rig_with(EffectsConfig())
    home_forces = rig.leg_forces_kn()
    assert np.all((home_forces > 8.5) & (home_forces < 9.7))
    for pose in workspace_poses(5, 1):
        rig.move_to_lengths(rig.controller_ik(pose))
        true = rig.true_pose()
        forces = rig.leg_forces_kn()
        np.testing.assert_allclose(forces, forces_by_virtual_work_kn(true), rtol=0, atol=1e-8)
        R = rotation_matrix(np.radians(true[3:]))
        legs = A_TRUE @ R.T + true[:3] - B_TRUE
        vertical_kn = np.sum(forces * legs[:, 2] / np.linalg.norm(legs, axis=1))
        assert vertical_kn == pytest.approx(ROBOT.moving_mass_kg * ROBOT.gravity_mps2 / 1000.0, rel=1e-12)


def test_leg_compliance_pose_is_self_consistent_with_the_loads_it_causes() -> None:
    c = np.array([0.2, 0.3, 0.25, 0.35, 0.15, 0.4])
    rig = rig_with(EffectsConfig(leg_compliance=LegComplianceConfig(enabled=True, c_mm_per_kn=c.tolist())))
    rigid = rig_with(EffectsConfig())
    for pose in workspace_poses(6, 2):
        reported = rig.controller_ik(pose)
        rig.move_to_lengths(reported)
        rigid.move_to_lengths(reported)
        true = rig.true_pose()
        expected = reported + DL0 - c * forces_by_virtual_work_kn(true)
        assert np.max(np.abs(leg_lengths(true) - expected)) < 1e-8
        assert np.max(np.abs(true[:3] - rigid.true_pose()[:3])) > 0.5


def test_sensor_scale_divides_the_reported_stroke_by_the_gain() -> None:
    g_ppm = np.array([500.0, -300.0, 200.0, 0.0, 1000.0, -800.0])
    rig = rig_with(EffectsConfig(sensor_scale=SensorScaleConfig(enabled=True, gain_error_ppm=g_ppm.tolist())))
    for pose in workspace_poses(5, 3):
        reported = rig.controller_ik(pose)
        rig.move_to_lengths(reported)
        true_stroke = (reported - ROBOT.l0) / (1 + g_ppm * 1e-6)
        assert np.max(np.abs(leg_lengths(rig.true_pose()) - (ROBOT.l0 + true_stroke + DL0))) < 1e-9


def test_thermal_expansion_at_a_fixed_temperature() -> None:
    effects = EffectsConfig(thermal_expansion=ThermalExpansionConfig(enabled=True, alpha_ppm_per_k=11.5))
    rig = rig_with(effects, temperature=FIXED_35C)
    for pose in workspace_poses(4, 4):
        reported = rig.controller_ik(pose)
        rig.move_to_lengths(reported)
        rig.advance_time(600.0)
        true = rig.true_pose()
        L = leg_lengths(true)
        assert rig.temperature_c() == 35.0
        assert np.max(np.abs(L - (reported + DL0 + 11.5e-6 * L * 15.0))) < 1e-9
        assert np.all(L - (reported + DL0) > 0.6)


def test_thermal_pose_follows_the_clock() -> None:
    drifting = TemperatureConfig(t0_c=20.0, drift_k_per_h=2.0, amplitude_k=0.0)
    rig = rig_with(EffectsConfig(thermal_expansion=ThermalExpansionConfig(enabled=True)), temperature=drifting)
    reported = rig.controller_ik(workspace_poses(1, 5)[0])
    rig.move_to_lengths(reported)
    z0 = rig.true_pose()[2]
    rig.advance_time(1800.0)
    assert rig.true_temperature_c() == pytest.approx(21.0)
    L = leg_lengths(rig.true_pose())
    assert np.max(np.abs(L - (reported + DL0) / (1 - 11.5e-6 * 1.0))) < 1e-9
    assert rig.true_pose()[2] - z0 == pytest.approx(11.5e-6 * 4300.0**2 / 3091.0, rel=0.3)


def test_backlash_remembers_the_direction_of_the_last_move_of_each_leg() -> None:
    b = np.array([0.02, 0.03, 0.04, 0.05, 0.06, 0.07])
    effects = EffectsConfig(joint_backlash=JointBacklashConfig(enabled=True, backlash_mm=b.tolist()))
    rig = rig_with(effects, leg_resolution_mm=0.0)
    start = rig.reported_lengths()
    np.testing.assert_array_equal(rig.motion_direction(), np.ones(6))
    steps = [
        (np.array([5.0, -5.0, 5.0, -5.0, 0.0, 0.0]), [1, -1, 1, -1, 1, 1]),
        (np.array([5.0, -5.0, 5.0, -5.0, 0.0, 0.0]) + 0.0009, [1, -1, 1, -1, 1, 1]),
        (np.array([-2.0, -5.0, 5.0, 2.0, -3.0, 0.0]), [-1, -1, 1, 1, -1, 1]),
        (np.array([-2.0, -4.0, 5.0, 2.0, -3.0 + 0.0002, -0.001]), [-1, 1, 1, 1, -1, -1]),
    ]
    for offset, want in steps:
        reported = start + offset
        rig.move_to_lengths(reported)
        np.testing.assert_array_equal(rig.motion_direction(), want)
        expected = reported + DL0 + np.array(want) * b / 2
        assert np.max(np.abs(leg_lengths(rig.true_pose()) - expected)) < 1e-9

    quantized = rig_with(effects)
    quantized.move_to_lengths(quantized.reported_lengths() - 0.003)
    quantized.move_to_lengths(quantized.reported_lengths() + 0.001)
    np.testing.assert_array_equal(quantized.motion_direction(), np.ones(6))


def test_backlash_hysteresis_and_batch_poses_follow_the_move_history() -> None:
    effects = EffectsConfig(joint_backlash=JointBacklashConfig(enabled=True, backlash_mm=0.05))
    rig = rig_with(effects)
    target = rig.controller_ik(workspace_poses(1, 6)[0])
    rig.move_to_lengths(target - 10.0)
    rig.move_to_lengths(target)
    from_below = leg_lengths(rig.true_pose())
    rig.move_to_lengths(target + 10.0)
    rig.move_to_lengths(target)
    np.testing.assert_allclose(from_below - leg_lengths(rig.true_pose()), 0.05, atol=1e-9)

    fresh = rig_with(effects)
    sequence = fresh.controller_ik(workspace_poses(5, 7))
    batch = fresh.true_poses_for_lengths(sequence)
    np.testing.assert_array_equal(fresh.motion_direction(), np.ones(6))
    for lengths, want in zip(sequence, batch, strict=True):
        fresh.move_to_lengths(lengths)
        np.testing.assert_allclose(fresh.true_pose(), want, atol=1e-8)


def test_oil_column_compliance_grows_with_the_stroke() -> None:
    kappa = np.array([0.5, 0.6, 0.7, 0.4, 0.3, 0.8])
    oil = OilColumnComplianceConfig(enabled=True, kappa_mm_per_kn_m=kappa.tolist(), dead_length_m=0.2)
    rig = rig_with(EffectsConfig(oil_column_compliance=oil))
    for pose in workspace_poses(5, 8):
        reported = rig.controller_ik(pose)
        rig.move_to_lengths(reported)
        true = rig.true_pose()
        column_m = (reported - ROBOT.l0) / 1000.0 + 0.2
        expected = reported + DL0 - kappa * forces_by_virtual_work_kn(true) * column_m
        assert np.max(np.abs(leg_lengths(true) - expected)) < 1e-8


def test_all_effects_together_add_up() -> None:
    c, g_ppm, b, kappa = 0.1, np.array([300.0, -200.0, 100.0, 50.0, -400.0, 250.0]), 0.04, 0.3
    effects = EffectsConfig(
        leg_compliance=LegComplianceConfig(enabled=True, c_mm_per_kn=c),
        sensor_scale=SensorScaleConfig(enabled=True, gain_error_ppm=g_ppm.tolist()),
        thermal_expansion=ThermalExpansionConfig(enabled=True, alpha_ppm_per_k=12.0, t_ref_c=20.0),
        joint_backlash=JointBacklashConfig(enabled=True, backlash_mm=b),
        oil_column_compliance=OilColumnComplianceConfig(enabled=True, kappa_mm_per_kn_m=kappa),
    )
    rig = rig_with(effects, temperature=FIXED_35C)
    for pose in workspace_poses(4, 9):
        reported = rig.controller_ik(pose)
        rig.move_to_lengths(reported)
        true = rig.true_pose()
        L, F = leg_lengths(true), forces_by_virtual_work_kn(true)
        stroke_mm = (reported - ROBOT.l0) / (1 + g_ppm * 1e-6)
        expected = (
            ROBOT.l0 + stroke_mm + DL0 - c * F + 12e-6 * L * 15.0 + rig.motion_direction() * b / 2
            - kappa * F * (stroke_mm / 1000.0 + 0.15)
        )
        assert np.max(np.abs(L - expected)) < 1e-8
        parts = rig.length_corrections_mm()
        assert set(parts) == set(EFFECT_NAMES)
        np.testing.assert_allclose(sum(parts.values()), L - reported - DL0, atol=1e-8)


# ---------------------------------------------------------------- clock and temperature


def test_temperature_drifts_is_seeded_and_read_with_noise() -> None:
    cfg = RigConfig(seed=5, errors=ERRORS).temperature
    assert cfg == RigConfig(seed=5, errors=ERRORS).temperature != RigConfig(seed=6, errors=ERRORS).temperature
    assert 20.0 <= cfg.t0_c <= 22.0 and 0.5 <= cfg.drift_k_per_h <= 2.0 and 3600.0 <= cfg.period_s <= 7200.0
    assert cfg.amplitude_k == 0.3 and cfg.sensor_noise_k == 0.05
    rig, twin = (SimulatedRig(ROBOT, RigConfig(seed=5, errors=ERRORS)) for _ in range(2))
    assert rig.time_s == 0.0 and rig.true_temperature_c() == pytest.approx(cfg.t0_c)
    rig.advance_time(1000.0)
    rig.advance_time(2000.0)
    twin.set_time(3000.0)
    expected = cfg.t0_c + cfg.drift_k_per_h * 3000.0 / 3600.0 + 0.3 * np.sin(2 * np.pi * 3000.0 / cfg.period_s)
    assert rig.time_s == 3000.0 and rig.true_temperature_c() == pytest.approx(expected, abs=1e-12)
    readings = np.array([rig.temperature_c() for _ in range(4000)])
    np.testing.assert_array_equal(readings, [twin.temperature_c() for _ in range(4000)])
    assert abs(readings.mean() - expected) < 0.005
    assert abs(readings.std(ddof=1) / 0.05 - 1) < 0.1
    with pytest.raises(ValueError, match="seconds"):
        rig.advance_time(-1.0)


def test_recording_carries_the_temperature_sensor() -> None:
    cfg = RigConfig(seed=2, errors=ERRORS)
    measure, verify = workspace_poses(10, 10), workspace_poses(2, 11)
    rec = simulate_recording(ROBOT, cfg, measure, verify, seconds_per_pose=120.0)
    np.testing.assert_allclose(rec.time_s, 120.0 * np.arange(1, 13))
    t = cfg.temperature
    periodic = t.amplitude_k * np.sin(2 * np.pi * rec.time_s / t.period_s)
    truth = t.t0_c + t.drift_k_per_h * rec.time_s / 3600.0 + periodic
    assert rec.temp_c is not None and rec.temp_c.shape == (12,)
    assert np.max(np.abs(rec.temp_c - truth)) < 5 * t.sensor_noise_k
    again = simulate_recording(ROBOT, cfg, measure, verify, seconds_per_pose=120.0)
    np.testing.assert_array_equal(again.temp_c, rec.temp_c)


# ---------------------------------------------------------------- CMM noise models


def _cmm_noise(model: str, n: int) -> tuple[np.ndarray, np.ndarray]:
    """n draws of the sphere-centre noise (n, 6, 3) and the noise-free centres (6, 3) in the CMM frame."""
    cmm = CmmPose(x_mm=3000.0, y_mm=-2500.0, z_mm=-500.0, roll_deg=1.0, pitch_deg=-2.0, yaw_deg=60.0)
    rig = SimulatedRig(
        ROBOT, RigConfig(seed=1, errors=ERRORS, cmm_noise_mm=0.01, cmm_pose=cmm, cmm_noise_model=model)
    )
    pose = rig.true_pose()
    Rc = rotation_matrix(np.radians([1.0, -2.0, 60.0]))
    R = rotation_matrix(np.radians(pose[3:]))
    truth = (np.vstack([ROBOT.platform_spheres @ R.T + pose[:3], ROBOT.base_spheres]) - [3000.0, -2500.0, -500.0]) @ Rc
    draws = np.array([np.vstack(rig.measure_spheres()) for _ in range(n)])
    return draws - truth, truth


def test_distance_noise_grows_with_the_distance_from_the_cmm() -> None:
    noise, truth = _cmm_noise("distance", 3000)
    sigma = 0.01 * (1 + np.linalg.norm(truth, axis=1) / 2000.0)
    assert sigma.max() / sigma.min() > 1.5
    np.testing.assert_allclose(noise.std(axis=0, ddof=1) / sigma[:, None], 1.0, atol=0.1)


def test_student_t_noise_has_the_configured_std_and_heavier_tails() -> None:
    gauss = _cmm_noise("gaussian", 5000)[0].ravel()
    heavy = _cmm_noise("student_t", 5000)[0].ravel()
    for sample in (gauss, heavy):
        assert abs(sample.std(ddof=1) / 0.01 - 1) < 0.1
    assert abs(kurtosis(gauss)) < 0.2
    assert kurtosis(heavy) > 2.0


# ---------------------------------------------------------------- configuration


def test_concealed_effects_are_single_seeded_and_of_tens_of_micrometres() -> None:
    poses = workspace_poses(20, 12)
    for name in EFFECT_NAMES:
        effects = concealed_effect_config(name, 1.0, seed=3)
        assert effects.active() == (name,)
        assert effects == concealed_effect_config(name, 1.0, seed=3) != concealed_effect_config(name, 1.0, seed=4)
        rig = rig_with(effects, seed=3)
        deltas = []
        for pose in poses:
            rig.advance_time(45.0)
            rig.move_to_lengths(rig.controller_ik(pose))
            deltas.append(rig.length_corrections_mm()[name])
        spread_um = 1000.0 * np.ptp(np.array(deltas), axis=0)
        assert 10.0 < spread_um.max() < 100.0, (name, spread_um)
    zero = concealed_effect_config("leg_compliance", 0.0, seed=3).leg_compliance.c_mm_per_kn
    assert zero == [0.0] * 6
    assert concealed_effect_config("none", 1.0, 0) == EffectsConfig()
    with pytest.raises(ValueError, match="unknown effect"):
        concealed_effect_config("friction", 1.0, 0)


def test_config_validation() -> None:
    assert RigConfig(errors=ERRORS).effects.active() == ()
    with pytest.raises(ValueError):
        EffectsConfig.model_validate({"friction": {"enabled": True}})
    with pytest.raises(ValueError):
        LegComplianceConfig(enabled=True, c_mm_per_kn=[0.1] * 5)
    with pytest.raises(ValueError, match=">= 0"):
        JointBacklashConfig(enabled=True, backlash_mm=-0.01)
    with pytest.raises(ValueError):
        RigConfig(errors=ERRORS, cmm_noise_model="laplace")
    with pytest.raises(ValueError):
        RigConfig(errors=ERRORS, cmm_noise_student_t_dof=2.0)
    with pytest.raises(ValueError):
        TemperatureConfig(period_s=0.0)
