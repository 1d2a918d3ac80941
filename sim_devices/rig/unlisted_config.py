"""Configuration of the rig's out-of-library effects and session effects (all off by default, units in the names).

"Out-of-library" means: none of the candidate effects of the calibration tool's diagnosis describes them, so a
diagnosis has to call them unexplained, locate them and still model them. Each is a correction Δl_i (mm) to the
true joint-centre distance of some legs; the formulas live in sim_devices.rig.unlisted_physics. The session effect
(zero_shift) is what re-homing between two recording sessions does to an incremental length measurement.
"""

from __future__ import annotations

from pydantic import Field, field_validator

from sim_devices.config_base import Effect, PerLeg, check_non_negative, check_positive


class TransducerBowConfig(Effect):
    """Bent or nonlinear length transducer: Δl_i = A_i sin(π (s_i - s_min,i) / (s_max,i - s_min,i)).

    s_i is the piston stroke, [s_min, s_max] the stroke range of the leg (leg limits minus l0). The bow is zero at
    both stroke ends, as the end-point linearity error of a transducer calibrated at its two ends is.
    """

    amplitude_mm: PerLeg = Field(default=0.05, description="bow at mid-stroke per leg (or one for all), mm")


class CyclicStrokeErrorConfig(Effect):
    """Cyclic error over the stroke (screw lead or encoder interpolation): Δl_i = A_i sin(2π s_i / P_i + φ_i)."""

    amplitude_mm: PerLeg = Field(default=0.01, description="amplitude per leg (or one for all), mm")
    period_mm: PerLeg = Field(default=20.0, description="period in stroke (screw lead, scale pitch) per leg, mm")
    phase_deg: PerLeg = Field(default=0.0, description="phase at zero stroke per leg, degrees")

    _positive = field_validator("period_mm")(check_positive)


class HookeJointOffsetConfig(Effect):
    """Base universal joint whose two axes do not intersect: the leg pivots about a point that moves with the joint.

    Δl_i = |p_i - b_i| - |p_i - c_i|, c_i = b_i + d_i n_i the foot of the axes' common normal (see
    sim_devices.rig.unlisted_physics for the derivation). The first axis is fixed in the base, perpendicular to the
    leg at the home pose, horizontal for axis_angle_deg = 0 and turned about the home leg direction otherwise.
    """

    offset_mm: PerLeg = Field(default=2.0, description="distance between the two joint axes per leg, mm (signed)")
    axis_angle_deg: PerLeg = Field(
        default=0.0, description="first axis turned about the home leg direction from horizontal, per leg, degrees"
    )


class LocalHeatingConfig(Effect):
    """One leg warms relative to ambient (e.g. next to the hydraulic power unit) after each power-on.

    T_i(t) - T_amb(t) = ΔT_i (1 - exp(-t / τ)), t the time since the rig's session started (power-on);
    Δl_i = α L_i (T_i - T_amb), L_i the current leg length. The ambient temperature sensor does not see it.
    """

    delta_t_k: PerLeg = Field(
        default_factory=lambda: [2.0, 0.0, 0.0, 0.0, 0.0, 0.0],
        description="final excess temperature of each leg over ambient, K",
    )
    time_constant_s: float = Field(default=1800.0, gt=0, description="thermal time constant τ of the leg, s")
    alpha_ppm_per_k: float = Field(default=11.5, description="expansion coefficient of the leg (steel), ppm/K")


class FrictionHysteresisConfig(Effect):
    """Friction hysteresis that grows with the size of the last move: Δl_i = h_i dir_i (1 - exp(-|Δ_i| / λ)).

    dir_i is the direction of the last move of leg i (+1 extending) and |Δ_i| its size in mm (moves below the
    1 µm direction deadband keep the previous state): a Dahl-like friction state that saturates after long moves.
    """

    amplitude_mm: PerLeg = Field(default=0.02, description="saturated offset h per leg (or one for all), mm")
    length_mm: float = Field(default=20.0, gt=0, description="move size λ over which the offset builds up, mm")

    _non_negative = field_validator("amplitude_mm")(check_non_negative)


class ZeroShiftConfig(Effect):
    """Re-homing: from the simulated time from_time_s on, the true length of leg i exceeds the reported one by s_i."""

    shift_mm: PerLeg = Field(default=0.005, description="zero shift per leg (or one for all), mm")
    from_time_s: float = Field(default=0.0, ge=0, description="rig clock from which the shift applies, s")


UNLISTED_EFFECT_NAMES = ("transducer_bow", "cyclic_stroke_error", "hooke_joint_offset", "local_heating")
"""Effects that no candidate of the calibration tool's diagnosis describes (in EffectsConfig field order)."""

PARTLY_LISTED_EFFECT_NAMES = ("friction_hysteresis",)
"""Effects whose larger part a library candidate describes: the direction term of friction_hysteresis is a
joint_backlash, and with rigid terms it explains 82-96 % of its variance over the study run (per leg, concealed
seeds 0-2, ``python examples/unlisted_ratios.py --overlap --seeds 3``); only the move-size part is outside."""

SESSION_EFFECT_NAMES = ("zero_shift",)
"""Effects of recording in several sessions."""

TIME_DEPENDENT_EFFECTS = frozenset({"thermal_expansion", "local_heating", "zero_shift", "leg_tables"})
"""Effects whose Δl changes when only the rig's clock moves."""
