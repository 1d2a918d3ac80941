"""Configuration of the rig's electric-leg effects: motor-encoder length measurement and drive compliance (all off).

An electric leg is a motor turning a screw (directly, through a belt and pulleys or a gearbox); the controller does
not measure the leg's length, it counts motor revolutions from a home switch and multiplies them by a configured mm
per revolution. The formulas live in sim_devices.rig.electric_physics. Magnitudes are datasheet-class figures for
a small hexapod (Ø12 mm ball screws, preloaded nuts, angular-contact bearings, home switches); each is stated with
its source below.
"""

from __future__ import annotations

import math

from pydantic import Field, field_validator

from sim_devices.config_base import Effect, PerLeg, check_non_negative, check_positive

STEEL_E_N_PER_MM2 = 210_000.0
"""Young's modulus of steel."""
BALL_SCREW_ROOT_DIAMETER_MM = 9.5
"""Root (core) diameter of a Ø12 mm ball screw with a 2-4 mm lead (catalogue value, e.g. 12x4: 9.5-10 mm)."""
BALL_SCREW_C_PER_LENGTH_MM_PER_KN_M = 1e6 / (math.pi * BALL_SCREW_ROOT_DIAMETER_MM**2 / 4 * STEEL_E_N_PER_MM2)
"""Axial compliance of that screw per metre between nut and fixed bearing, 1 / (A E) in mm/(kN m): about 0.067
(1000 mm × 1000 N / (71 mm² × 210000 N/mm²))."""
NUT_AND_BEARING_C_MM_PER_KN = 0.02
"""A preloaded small ball nut (~100 N/µm) in series with a fixed angular-contact bearing pair (~100 N/µm)."""
BELT_C_PER_LENGTH_MM_PER_KN_M = (3.6, 11.0)
"""A belt-driven leg: 10 mm wide steel-cord polyurethane timing belts (T5, AT5, ATL5) have a specific spring rate of
9e4-2.75e5 N per unit strain (manufacturers' catalogues), i.e. 3.6-11 mm/(kN m), 50-170 times the screw's;
narrower or glass-cord belts are softer."""
HOME_SWITCH_REPEATABILITY_MM = 0.002
"""1σ of a mechanical or inductive home switch's trip point (datasheets: 1-5 µm; with an encoder index pulse < 1 µm)."""


class MotorEncoderConfig(Effect):
    """Leg length from motor revolutions: the controller reports l0 + s_home + n · lead_configured.

    n is the screw revolutions counted since the home switch tripped at the start of the session; the leg really
    travels n · lead_true from there. lead_ratio = lead_true / lead_configured per leg: 1.0625 means the leg moves
    6.25 % more than the controller counts (a mis-set lead, pulley or gear ratio: a 16-tooth motor pulley
    configured as 15), 0.9375 that the leg reads 6.67 % long. At each homing (power-on: SimulatedRig.start_session)
    the switch trips at a true stroke that differs from s_home by a seeded N(0, homing_repeatability_mm²) per leg
    and session. Within each revolution the screw's periodic lead error adds A sin(2π u / lead + φ), u the true
    travel from the nominal switch point (ground screws of ISO 3408 classes 3-5: a few µm peak to peak).
    """

    lead_ratio: PerLeg = Field(default=1.0, description="true / configured mm per revolution, per leg (or one)")
    lead_mm: PerLeg = Field(default=2.0, description="true screw lead, mm per revolution (period of the pitch error)")
    home_stroke_mm: PerLeg = Field(
        default=0.0, description="stroke at which the home switch trips (the controller then reports l0 + this), mm"
    )
    homing_repeatability_mm: float = Field(
        default=HOME_SWITCH_REPEATABILITY_MM, ge=0, description="1σ of the switch's trip point per session and leg, mm"
    )
    pitch_error_mm: PerLeg = Field(default=0.0, description="amplitude of the periodic error within one revolution, mm")
    pitch_phase_deg: PerLeg = Field(default=0.0, description="phase of the periodic error at the nominal switch point")

    _positive = field_validator("lead_ratio", "lead_mm")(check_positive)
    _non_negative = field_validator("pitch_error_mm")(check_non_negative)


class DriveComplianceConfig(Effect):
    """Axial compliance of an electric leg's drive, growing with the screw's free length: Δl_i = -c_i F_i.

    c_i = c_fixed + c_per_length · (free_length_at_zero_stroke + s_i), s_i the true stroke (mm → m), F_i the
    axial compression (kN) from the platform statics. The screw's FIXED bearing is at the motor, at the BASE end
    of the leg, and the nut rides on the push rod: extending the leg moves the nut away from the bearing, so the
    loaded length of screw between them grows with the stroke. c_fixed holds what does not depend on the stroke
    (nut, bearings, coupling or belt reduction, joints). Defaults: a Ø12 mm steel ball screw (about
    0.067 mm/(kN m)) with a preloaded nut and bearing pair (0.02 mm/kN): on a light platform (a few newtons per
    leg) a sag below 0.2 µm, of which tens of nanometres change over a 50 mm stroke. A belt-driven leg is
    3.6-11 mm/(kN m) (BELT_C_PER_LENGTH_MM_PER_KN_M). The near-alias option is a drive far softer than that (tens
    to hundreds of mm/(kN m): a slack or damaged drive, or simply a deliberately large test value), whose term is
    then big enough to matter and, as F changes with the pose by a fraction of its mean only, mostly
    mean(F) · s: a near-alias of a scale error (drive_compliance_for_signature gives the value for a chosen size).
    """

    c_fixed_mm_per_kn: PerLeg = Field(
        default=NUT_AND_BEARING_C_MM_PER_KN, description="compliance that does not depend on the stroke, mm/kN"
    )
    c_per_length_mm_per_kn_m: PerLeg = Field(
        default=BALL_SCREW_C_PER_LENGTH_MM_PER_KN_M,
        description="compliance per metre of free screw (or belt) between nut and fixed bearing, mm/(kN m)",
    )
    free_length_at_zero_stroke_mm: PerLeg = Field(
        default=30.0, description="free screw length between fixed bearing and nut at zero stroke, mm"
    )

    _non_negative = field_validator(
        "c_fixed_mm_per_kn", "c_per_length_mm_per_kn_m", "free_length_at_zero_stroke_mm"
    )(check_non_negative)


def drive_compliance_for_signature(signature_mm: float, load_kn: float, stroke_range_mm: float) -> float:
    """c_per_length (mm/(kN m)) whose load × stroke term spans signature_mm over the stroke range at this load.

    The near-alias setting: on a light platform the load hardly changes with the pose, so this term is mostly a
    stroke-proportional one of slope signature / stroke range, i.e. a scale error of that size.
    """
    if load_kn <= 0 or stroke_range_mm <= 0:
        raise ValueError(f"load_kn and stroke_range_mm must be > 0, got {load_kn}, {stroke_range_mm}")
    return signature_mm / (load_kn * stroke_range_mm / 1000.0)


ELECTRIC_EFFECT_NAMES = ("motor_encoder", "drive_compliance")
"""Effects of electric legs (in EffectsConfig field order)."""
