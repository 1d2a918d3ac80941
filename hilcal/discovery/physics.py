"""The library of named physics that a rigid geometric model leaves out, each linear in its parameters.

Every effect corrects the geometric length of each leg (see `hilcal.discovery.term_groups`); the constant part of
any correction is absorbed by dl0, so only its variation over the poses can be seen. Each effect declares
the physically possible range of its parameters, scaled from the robot file and the recording (leg length,
stroke range, largest axial load), so the same library serves a 4-tonne hydraulic platform and a small
electric hexapod. A fit outside that range is not named as the effect.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from hilcal.discovery.context import EffectContext
from hilcal.discovery.term_groups import LIBRARY, PhysicalRange, TermGroup, per_leg_diagonal
from hilcal.kinematics import Geometry, inverse_kinematics
from hilcal.robot import Robot

MIN_TEMPERATURE_RANGE_K = 0.2
REFERENCE_TEMPERATURE_C = 20.0
"""ISO 1 reference temperature: the nominal geometry is taken to hold at 20 °C."""
MAX_STATIC_STRAIN = 0.01
"""A leg that shortens by more than 1 % of its length under the platform's weight is not a structural
member (1 % is the strain of hydraulic oil at ~15 MPa, far above any static load)."""
MAX_GAIN_ERROR_PPM = 5000.0
"""Beyond 0.5 % a length transducer is broken or mis-configured, not mis-calibrated."""
ALPHA_RANGE_PPM_PER_K = (0.0, 30.0)
"""Invar (~1 ppm/K) to aluminium (23 ppm/K), with margin; legs do not shrink when they warm."""
MAX_BACKLASH_FRACTION = 0.002
MIN_BACKLASH_BOUND_MM = 0.01
MAX_ZERO_SHIFT_FRACTION = 0.02


@dataclass(frozen=True)
class RobotScales:
    """Sizes that set the physical ranges: leg length, stroke range and the largest axial load."""

    leg_length_mm: float
    stroke_range_mm: float
    max_load_kn: float

    @classmethod
    def of(cls, robot: Robot, ctx: EffectContext) -> RobotScales:
        lo, hi = robot.leg_limits
        home = inverse_kinematics(Geometry.nominal(robot), robot.home)
        weight_kn = robot.moving_mass_kg * robot.gravity_mps2 / 1000.0
        load = max(float(np.max(np.abs(ctx.force_kn))), weight_kn / 6.0)
        return cls(float(np.mean(home)), float(hi - lo), load)


@dataclass(frozen=True)
class Candidate:
    """A documented physical effect: parameters with units, regressors, physical range, the naming sentence."""

    name: str
    title: str
    unit: str
    sentence: str
    driver: str
    regressor: Callable[[EffectContext], np.ndarray]
    limits: Callable[[RobotScales], tuple[float, float, str]]
    per_leg: bool = True
    applicable: Callable[[EffectContext], str | None] = lambda ctx: None

    def parameter_names(self) -> tuple[str, ...]:
        if self.per_leg:
            return tuple(f"leg{i + 1}_{self.name}_{self.unit}" for i in range(6))
        return (f"{self.name}_{self.unit}",)

    def bind(self, ctx: EffectContext, scales: RobotScales) -> TermGroup:
        names = self.parameter_names()
        lo, hi, why = self.limits(scales)
        return TermGroup(
            key=self.name, kind=LIBRARY, effect=self.name, title=self.title, names=names, phi=self.regressor,
            physical_range=PhysicalRange(np.full(len(names), lo), np.full(len(names), hi), why),
            sentence=self.sentence, variable=self.driver,
        )


def _thermal_applicable(ctx: EffectContext) -> str | None:
    if ctx.temp_c is None:
        return "no temp_c column in the recording"
    span = float(np.ptp(ctx.temp_c))
    if span < MIN_TEMPERATURE_RANGE_K:
        return f"temperature varied only {span:.2f} K; leg growth cannot be told from a transducer scale error"
    return None


def _thermal(ctx: EffectContext) -> np.ndarray:
    """Leg growth alpha * L * (T - 20 °C): a drift over the run plus a scale-like offset, one parameter."""
    assert ctx.temp_c is not None
    dt = ctx.temp_c - REFERENCE_TEMPERATURE_C
    return (ctx.legs_mm * dt[:, None] * 1e-6)[:, :, None]


def _backlash_applicable(ctx: EffectContext) -> str | None:
    known = ctx.direction != 0
    both = [(np.any(ctx.direction[known[:, i], i] > 0) and np.any(ctx.direction[known[:, i], i] < 0))
            for i in range(6)]
    if not any(both):
        return "every pose was approached from the same direction, so backlash is constant and absorbed by dl0"
    return None


def _compliance_limits(s: RobotScales) -> tuple[float, float, str]:
    high = 1000.0 * MAX_STATIC_STRAIN * s.leg_length_mm / s.max_load_kn
    return 0.0, high, (f"a leg only shortens under compression (c >= 0), and by at most {MAX_STATIC_STRAIN:.0%} of its "
                       f"{s.leg_length_mm:.0f} mm length at the largest load of {s.max_load_kn:.3g} kN")


def _oil_limits(s: RobotScales) -> tuple[float, float, str]:
    high = 1000.0 * MAX_STATIC_STRAIN * s.leg_length_mm / (s.max_load_kn * s.stroke_range_mm / 1000.0)
    return 0.0, high, ("the oil column only softens a leg (kappa >= 0), and the sag at full stroke and the largest "
                       f"load stays below {MAX_STATIC_STRAIN:.0%} of the leg length")


def _scale_limits(s: RobotScales) -> tuple[float, float, str]:
    return -MAX_GAIN_ERROR_PPM, MAX_GAIN_ERROR_PPM, (
        f"a working transducer's gain error is below {MAX_GAIN_ERROR_PPM:.0f} ppm (0.5 %)")


def _thermal_limits(s: RobotScales) -> tuple[float, float, str]:
    lo, hi = ALPHA_RANGE_PPM_PER_K
    return lo, hi, f"structural metals expand by {lo:g}-{hi:g} ppm/K (invar to aluminium, with margin)"


def _backlash_limits(s: RobotScales) -> tuple[float, float, str]:
    bound = max(MAX_BACKLASH_FRACTION * s.stroke_range_mm, MIN_BACKLASH_BOUND_MM)
    return -bound, bound, (f"play of at most {bound:.3g} mm ({MAX_BACKLASH_FRACTION:.1%} of the "
                           f"{s.stroke_range_mm:.0f} mm stroke range); the sign depends on where the transducer "
                           "sits relative to the play, so both signs are physical")


CANDIDATES: tuple[Candidate, ...] = (
    Candidate(
        "leg_compliance", "leg compliance under gravity", "um_per_kN",
        "the legs shorten under the platform's weight (axial compliance); the load on each leg changes with "
        "the pose, so the platform sags by different amounts across the workspace",
        "axial load (kN)", lambda ctx: per_leg_diagonal(-ctx.force_kn * 1e-3), _compliance_limits,
    ),
    Candidate(
        "sensor_scale", "leg-length transducer scale (gain) error", "ppm",
        "the leg-length transducers over- or under-read in proportion to the stroke (a gain error)",
        "stroke (mm)", lambda ctx: per_leg_diagonal(-ctx.stroke_mm * 1e-6), _scale_limits,
    ),
    Candidate(
        "thermal_expansion", "thermal expansion of the legs", "ppm_per_K",
        "the legs grow with temperature, so the same reported length gives a longer leg as the machine warms",
        "temperature (°C)", _thermal, _thermal_limits, per_leg=False, applicable=_thermal_applicable,
    ),
    Candidate(
        "joint_backlash", "joint backlash (depends on the direction of the last leg motion)", "mm",
        "the leg length depends on the direction from which each leg approached the pose (play in the "
        "joints or the transducer coupling)",
        "direction of last motion", lambda ctx: per_leg_diagonal(0.5 * ctx.direction), _backlash_limits,
        applicable=_backlash_applicable,
    ),
    Candidate(
        "oil_column_compliance", "hydraulic oil-column compliance (grows with stroke)", "um_per_kN_m",
        "the hydraulic legs are softer when extended: the compressed oil column grows with the stroke, so "
        "the sag under load grows with leg extension",
        "axial load x stroke (kN m)", lambda ctx: per_leg_diagonal(-ctx.force_kn * ctx.stroke_mm * 1e-6),
        _oil_limits,
    ),
)

CANDIDATES_BY_NAME = {c.name: c for c in CANDIDATES}
ZERO_SHIFT = "session_zero_shift"
ZERO_SHIFT_TITLE = "leg zero shift between sessions (re-homing)"


def zero_shift_group(ctx: EffectContext, scales: RobotScales) -> TermGroup | None:
    """Per-leg offsets of every later session of the fitted rows against the first: a re-homing or zero shift."""
    sessions = np.unique(ctx.session)
    if sessions.size < 2:
        return None
    later = sessions[1:]

    def phi(c: EffectContext) -> np.ndarray:
        return np.concatenate([per_leg_diagonal(c.per_leg(c.session == s)) for s in later], axis=2)

    names = tuple(f"leg{i + 1}_zero_shift_session{s + 1}_mm" for s in later for i in range(6))
    bound = MAX_ZERO_SHIFT_FRACTION * scales.stroke_range_mm
    return TermGroup(
        key=ZERO_SHIFT, kind=LIBRARY, effect=ZERO_SHIFT, title=ZERO_SHIFT_TITLE, names=names, phi=phi,
        physical_range=PhysicalRange(np.full(len(names), -bound), np.full(len(names), bound),
                                     f"a zero shift stays within {MAX_ZERO_SHIFT_FRACTION:.0%} of the stroke range"),
        sentence="each leg's length reading jumped by a constant between sessions (the machine was re-homed, "
                 "or a transducer's zero shifted)", variable="session",
    )


def library_groups(ctx: EffectContext, robot: Robot) -> tuple[list[TermGroup], dict[str, str]]:
    """The applicable library effects bound to the fitted rows, and why the others cannot be tested."""
    scales = RobotScales.of(robot, ctx)
    groups, untestable = [], {}
    for cand in CANDIDATES:
        reason = cand.applicable(ctx)
        if reason is None:
            groups.append(cand.bind(ctx, scales))
        else:
            untestable[cand.name] = reason
    shift = zero_shift_group(ctx, scales)
    if shift is not None:
        groups.append(shift)
    return groups, untestable
