"""Non-geometric truth physics of the simulated rig: platform statics, leg-length effects, temperature, CMM noise.

Written independently of the calibration code (only the declarative robot is shared by the rig): the
statics solve the 6x6 equilibrium of the platform directly, in newtons and millimetres, with the true
joint geometry of the rig. Every effect is a correction Δl_i (mm) added to the true joint-centre distance
of leg i; the rig solves its forward kinematics with these corrections until the pose is self-consistent.
"""

from __future__ import annotations

import numpy as np

from sim_devices.rig.config import EffectsConfig, TemperatureConfig, per_leg

DIRECTION_DEADBAND_MM = 1e-3
DEADBAND_ROUNDING_MM = 1e-9
SECONDS_PER_HOUR = 3600.0
PPM = 1e-6
MM_PER_M = 1000.0
N_PER_KN = 1000.0


def platform_joints_mm(rotation: np.ndarray, t_mm: np.ndarray, a_mm: np.ndarray) -> np.ndarray:
    """(6, 3) platform joints in the base frame for a rotation matrix (3, 3) and a translation (3,)."""
    return a_mm @ rotation.T + t_mm


def axial_leg_forces_kn(
    rotation: np.ndarray,
    t_mm: np.ndarray,
    a_mm: np.ndarray,
    b_mm: np.ndarray,
    mass_kg: float,
    com_mm: np.ndarray,
    gravity_mps2: float,
) -> np.ndarray:
    """Axial leg forces (kN, compression positive) holding the moving mass at this pose.

    A compressed leg pushes the platform along u_i, the unit vector from its base joint b_i to its
    platform joint p_i. Equilibrium of forces and of moments about the base origin:
    sum_i F_i u_i + W = 0 and sum_i F_i p_i x u_i + c x W = 0, with W = (0, 0, -m g) acting at the centre
    of mass c (base frame).
    """
    p = platform_joints_mm(rotation, t_mm, a_mm)
    legs = p - b_mm
    u = legs / np.linalg.norm(legs, axis=1, keepdims=True)
    wrench_map = np.vstack([u.T, np.cross(p, u).T])
    com = rotation @ com_mm + t_mm
    weight_n = np.array([0.0, 0.0, -mass_kg * gravity_mps2])
    rhs = -np.concatenate([weight_n, np.cross(com, weight_n)])
    return np.linalg.solve(wrench_map, rhs) / N_PER_KN


def leg_temperature_c(config: TemperatureConfig, time_s: float) -> float:
    """True leg (= ambient) temperature: T0 + drift t / 3600 + A sin(2 pi t / period), °C, or the recorded history
    interpolated at time_s (held at its ends)."""
    if config.table_time_s is not None and config.table_c is not None:
        return float(np.interp(time_s, config.table_time_s, config.table_c))
    return float(
        config.t0_c
        + config.drift_k_per_h * time_s / SECONDS_PER_HOUR
        + config.amplitude_k * np.sin(2.0 * np.pi * time_s / config.period_s)
    )


def motion_direction(previous: np.ndarray, step_mm: np.ndarray) -> np.ndarray:
    """Per-leg direction of the last motion (+1 extending, -1 retracting); moves below 1 µm keep the old one.

    A quantized 1 µm step (e.g. 4300.001 - 4300.000, a little below 1e-3 in floating point) counts as a move.
    """
    moved = np.abs(step_mm) >= DIRECTION_DEADBAND_MM - DEADBAND_ROUNDING_MM
    return np.where(moved, np.sign(step_mm), previous)


def true_stroke_mm(reported_mm: np.ndarray, l0_mm: np.ndarray, effects: EffectsConfig) -> np.ndarray:
    """Piston stroke (mm): the reported stroke divided by the transducer gain (1 + g) when sensor_scale is on."""
    stroke = np.asarray(reported_mm, dtype=float) - l0_mm
    if effects.sensor_scale.enabled:
        stroke = stroke / (1.0 + per_leg(effects.sensor_scale.gain_error_ppm) * PPM)
    return stroke


def length_corrections_mm(
    effects: EffectsConfig,
    *,
    reported_mm: np.ndarray,
    l0_mm: np.ndarray,
    leg_lengths_mm: np.ndarray,
    forces_kn: np.ndarray,
    temperature_c: float,
    direction: np.ndarray,
) -> dict[str, np.ndarray]:
    """Δl (mm, (6,)) of every enabled effect, to add to reported + dl0.

    leg_lengths_mm are the current joint-centre distances and forces_kn the axial compressions at the
    current pose; direction is the last motion direction of each leg.
    """
    out: dict[str, np.ndarray] = {}
    reported = np.asarray(reported_mm, dtype=float)
    stroke_mm = true_stroke_mm(reported, l0_mm, effects)
    if effects.leg_compliance.enabled:
        out["leg_compliance"] = -per_leg(effects.leg_compliance.c_mm_per_kn) * forces_kn
    if effects.sensor_scale.enabled:
        out["sensor_scale"] = stroke_mm - (reported - l0_mm)
    if effects.thermal_expansion.enabled:
        cfg = effects.thermal_expansion
        out["thermal_expansion"] = per_leg(cfg.alpha_ppm_per_k) * PPM * leg_lengths_mm * (temperature_c - cfg.t_ref_c)
    if effects.joint_backlash.enabled:
        out["joint_backlash"] = direction * per_leg(effects.joint_backlash.backlash_mm) / 2.0
    if effects.oil_column_compliance.enabled:
        cfg = effects.oil_column_compliance
        column_m = stroke_mm / MM_PER_M + cfg.dead_length_m
        out["oil_column_compliance"] = -per_leg(cfg.kappa_mm_per_kn_m) * forces_kn * column_m
    return out


def cmm_noise_mm(
    rng: np.random.Generator,
    points_cmm_mm: np.ndarray,
    sigma0_mm: float,
    model: str,
    *,
    reference_distance_mm: float,
    student_t_dof: float,
) -> np.ndarray:
    """Noise to add to points (M, 3) in the CMM frame for the non-Gaussian models.

    distance: Gaussian with sigma = sigma0 (1 + d / d_ref), d the point's distance from the CMM origin;
    student_t: Student-t with the given degrees of freedom, scaled so its std is sigma0.
    """
    if model == "distance":
        sigma = sigma0_mm * (1.0 + np.linalg.norm(points_cmm_mm, axis=-1, keepdims=True) / reference_distance_mm)
        return rng.normal(0.0, 1.0, points_cmm_mm.shape) * sigma
    if model == "student_t":
        scale = sigma0_mm / np.sqrt(student_t_dof / (student_t_dof - 2.0))
        return rng.standard_t(student_t_dof, points_cmm_mm.shape) * scale
    raise ValueError(f"unknown CMM noise model {model!r}")
