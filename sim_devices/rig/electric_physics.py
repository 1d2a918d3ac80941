"""Truth physics of electric legs: length counted from motor revolutions, homing per session, drive compliance.

Written for the simulator, apart from the calibration tool's models. Per leg, with s_rep = reported - l0 the
stroke the controller reports and s_home the stroke at which the home switch is meant to trip:

- the controller counts n = (s_rep - s_home) / lead_configured screw revolutions since homing;
- at this session's homing the switch tripped at the true stroke s_home + e (e: the switch's repeatability, a
  seeded draw per session and leg), and the leg has since travelled n · lead_true, so the true stroke is
  s_true = s_home + e + r (s_rep - s_home) + p(u), r = lead_true / lead_configured, u = e + r (s_rep - s_home) the
  true travel from the nominal switch point, p(u) = A sin(2π u / lead_true + φ) the screw's periodic lead error;
- the drive deflects under the axial compression F (kN): -(c_fixed + c_per_length (L_free + s_true)) F, the free
  screw length growing with the stroke (fixed bearing at the base end, see DriveComplianceConfig).

The rig adds these Δl to the joint-centre distance reported + dl0 and solves the self-consistent pose.
"""

from __future__ import annotations

import numpy as np

from sim_devices.config_base import per_leg
from sim_devices.rig import physics
from sim_devices.rig.config import EffectsConfig
from sim_devices.rig.electric_config import DriveComplianceConfig, MotorEncoderConfig

MM_PER_M = 1000.0
HOMING_STREAM = 0x40E
"""Tag of the homing draws' random stream: default_rng([rig seed, HOMING_STREAM, session])."""


def homing_offsets_mm(seed: int, session: int, repeatability_mm: float) -> np.ndarray:
    """(6,) true stroke minus s_home at which each leg's switch tripped in this session (seeded per session)."""
    if session < 0:
        raise ValueError(f"session must be >= 0, got {session}")
    return np.random.default_rng([seed, HOMING_STREAM, session]).normal(0.0, 1.0, 6) * repeatability_mm


def encoder_stroke_error_mm(
    cfg: MotorEncoderConfig, reported_stroke_mm: np.ndarray, homing_offset_mm: np.ndarray
) -> np.ndarray:
    """s_true - s_rep (mm, (6,)): homing offset, lead-ratio error over the travel since the switch, pitch error."""
    s_rep = np.asarray(reported_stroke_mm, dtype=float)
    s_home, ratio = per_leg(cfg.home_stroke_mm), per_leg(cfg.lead_ratio)
    travel_mm = homing_offset_mm + ratio * (s_rep - s_home)
    pitch = per_leg(cfg.pitch_error_mm) * np.sin(
        2.0 * np.pi * travel_mm / per_leg(cfg.lead_mm) + np.radians(per_leg(cfg.pitch_phase_deg))
    )
    return s_home + travel_mm + pitch - s_rep


def drive_compliance_mm(cfg: DriveComplianceConfig, forces_kn: np.ndarray, true_stroke_mm: np.ndarray) -> np.ndarray:
    """-(c_fixed + c_per_length (L_free + s_true)) F: the drive shortens under compression, more when extended."""
    free_m = (per_leg(cfg.free_length_at_zero_stroke_mm) + np.asarray(true_stroke_mm, dtype=float)) / MM_PER_M
    compliance = per_leg(cfg.c_fixed_mm_per_kn) + per_leg(cfg.c_per_length_mm_per_kn_m) * free_m
    return -compliance * np.asarray(forces_kn, dtype=float)


def electric_corrections_mm(
    effects: EffectsConfig,
    *,
    reported_mm: np.ndarray,
    l0_mm: np.ndarray,
    forces_kn: np.ndarray,
    seed: int,
    session: int,
) -> dict[str, np.ndarray]:
    """Δl (mm, (6,)) of every enabled electric effect.

    session counts the homings (0 at the rig's power-on, +1 at every SimulatedRig.start_session); the drive's free
    length follows the true stroke, encoder error included.
    """
    out: dict[str, np.ndarray] = {}
    reported_stroke = np.asarray(reported_mm, dtype=float) - l0_mm
    if effects.motor_encoder.enabled:
        cfg = effects.motor_encoder
        offsets = homing_offsets_mm(seed, session, cfg.homing_repeatability_mm)
        out["motor_encoder"] = encoder_stroke_error_mm(cfg, reported_stroke, offsets)
    if effects.drive_compliance.enabled:
        stroke = true_stroke_mm(reported_mm, l0_mm, effects, out)
        out["drive_compliance"] = drive_compliance_mm(effects.drive_compliance, forces_kn, stroke)
    return out


def true_stroke_mm(
    reported_mm: np.ndarray, l0_mm: np.ndarray, effects: EffectsConfig, electric: dict[str, np.ndarray]
) -> np.ndarray:
    """The true stroke (mm, (6,)): the reported one corrected by the transducer gain and the motor encoder's error."""
    stroke = physics.true_stroke_mm(reported_mm, l0_mm, effects)
    return stroke + electric["motor_encoder"] if "motor_encoder" in electric else stroke
