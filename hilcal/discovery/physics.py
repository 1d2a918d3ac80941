"""The library of named physics that a rigid geometric model leaves out, each linear in its parameters.

Every effect corrects the geometric length of each leg (see `hilcal.discovery.term_groups`); the constant part of
any correction is absorbed by dl0, so only its variation over the poses can be seen. Each effect says which
machines it can occur on (the robot file's ``[actuators]``: an oil column only in hydraulic legs, a screw or belt
only in electric ones) and grades its parameters: typical values (physics), abnormal but possible values (a fault
of the set-up, with what to check) and impossible ones (never named). The bounds are scaled from the robot file
and the recording (leg length, stroke range, largest axial load) and each states its source, so the same library
serves a 4-tonne hydraulic platform and a small electric hexapod.
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
ELASTIC_STRAIN = 0.001
"""Steel strains elastically up to ~0.1 % (yield 210-250 MPa over E = 210 GPa): a leg that sags more under the
platform's weight has a mechanism in its load path (a loose joint or bearing, air in the oil)."""
MAX_STATIC_STRAIN = 0.01
"""A leg that shortens by more than 1 % of its length under the platform's weight is not a structural
member (1 % is the strain of hydraulic oil at ~15 MPa, far above any static load)."""
TYPICAL_GAIN_PPM = 1000.0
"""Calibrated leg-length sensing: magnetostrictive gradient ±0.05 %, LVDT or linear-scale gain ±0.1 %; ball-screw
lead ISO 3408-3 class C10 ±210 µm per 300 mm (700 ppm), toothed-belt pitch ±0.1 %."""
MAX_GAIN_ERROR_PPM = 500_000.0
"""A reading off by more than half its travel is not a scale: the machine would not reach its workspace and the
leg limits would trip (a sign or unit mix-up)."""
ALPHA_RANGE_PPM_PER_K = (0.0, 30.0)
"""Invar (~1 ppm/K) to aluminium (23 ppm/K), with margin; legs do not shrink when they warm."""
TYPICAL_BACKLASH_PER_MM = 5e-5
MIN_TYPICAL_BACKLASH_MM = 0.005
"""Play of precision spherical or universal joints: about 0.05 mm per metre of leg, at least 5 µm."""
MAX_BACKLASH_FRACTION = 0.002
MIN_BACKLASH_BOUND_MM = 0.01
TYPICAL_OIL_UM_PER_KN_M = 2000.0
"""1 / (A K) of an oil column: a 25 mm bore with an effective bulk modulus of 1 GPa (oil and hose) is ~2000
µm/(kN m); larger bores are stiffer."""
TYPICAL_DRIVE_UM_PER_KN_M = 5000.0
"""1 / (E A) per metre of free drive length: an 8 mm ball-screw shaft ~100 µm/(kN m), a 10 mm steel-cord
toothed belt ~5000 µm/(kN m)."""
TYPICAL_ZERO_SHIFT_MM = {"linear": 0.005, "motor_encoder": 0.02, None: 0.02}
"""Between sessions an absolute length transducer keeps its zero (electronics drift of a few µm); a motor encoder
is re-homed at a switch and index pulse (repeatability ~0.01-0.02 mm)."""
MAX_ZERO_SHIFT_FRACTION = 0.02


@dataclass(frozen=True)
class RobotScales:
    """Sizes that set the graded ranges: leg length, stroke range, the largest axial load and the machine's kind."""

    leg_length_mm: float
    stroke_range_mm: float
    max_load_kn: float
    kind: str | None = None
    transducer: str | None = None

    @classmethod
    def of(cls, robot: Robot, ctx: EffectContext) -> RobotScales:
        lo, hi = robot.leg_limits
        home = inverse_kinematics(Geometry.nominal(robot), robot.home)
        weight_kn = robot.moving_mass_kg * robot.gravity_mps2 / 1000.0
        load = max(float(np.max(np.abs(ctx.force_kn))), weight_kn / 6.0)
        return cls(float(np.mean(home)), float(hi - lo), load, robot.actuator_kind, robot.transducer)


@dataclass(frozen=True)
class Grade:
    """Typical and possible bounds of one effect's parameters with their sources, and what a fault means."""

    typical: tuple[float, float]
    possible: tuple[float, float]
    typical_why: str
    possible_why: str
    fault_check: str = ""

    def range_for(self, n: int) -> PhysicalRange:
        typical_lo, typical_hi = max(self.typical[0], self.possible[0]), min(self.typical[1], self.possible[1])
        graded = self.typical != self.possible
        return PhysicalRange(
            np.full(n, self.possible[0]), np.full(n, self.possible[1]), self.possible_why,
            np.full(n, typical_lo) if graded else None, np.full(n, typical_hi) if graded else None,
            self.typical_why if graded else "", self.fault_check,
        )


@dataclass(frozen=True)
class Candidate:
    """A documented physical effect: parameters with units, regressors, graded range, the machines it occurs on."""

    name: str
    title: str
    unit: str
    sentence: str
    driver: str
    regressor: Callable[[EffectContext], np.ndarray]
    grade: Callable[[RobotScales], Grade]
    per_leg: bool = True
    applicable: Callable[[EffectContext], str | None] = lambda ctx: None
    kinds: tuple[str, ...] = ("hydraulic", "electric")
    """Actuator kinds whose legs can have this effect."""
    same_signature_as: str | None = None
    """Another candidate with the same regressor (on a machine of unknown kind only one of them is tested)."""
    history: bool = False
    """The regressor depends on the motion history (unknown at a session's first row)."""

    def parameter_names(self) -> tuple[str, ...]:
        if self.per_leg:
            return tuple(f"leg{i + 1}_{self.name}_{self.unit}" for i in range(6))
        return (f"{self.name}_{self.unit}",)

    def title_for(self, kind: str | None) -> str:
        """The title, with the condition on the machine's kind when the robot file does not declare it."""
        if kind is None and len(self.kinds) == 1:
            return f"{self.title} (if the legs are {self.kinds[0]})"
        return self.title

    def bind(self, ctx: EffectContext, scales: RobotScales) -> TermGroup:
        names = self.parameter_names()
        return TermGroup(
            key=self.name, kind=LIBRARY, effect=self.name, title=self.title_for(scales.kind), names=names,
            phi=self.regressor, physical_range=self.grade(scales).range_for(len(names)), sentence=self.sentence,
            variable=self.driver, history=self.history,
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


def _compliance_grade(s: RobotScales) -> Grade:
    typical = 1000.0 * ELASTIC_STRAIN * s.leg_length_mm / s.max_load_kn
    high = 1000.0 * MAX_STATIC_STRAIN * s.leg_length_mm / s.max_load_kn
    return Grade(
        (0.0, typical), (0.0, high),
        f"an elastic leg sags at most {ELASTIC_STRAIN:.1%} of its {s.leg_length_mm:.0f} mm length at the largest "
        f"load of {s.max_load_kn:.3g} kN (steel's elastic strain)",
        f"a leg only shortens under compression (c >= 0), and by at most {MAX_STATIC_STRAIN:.0%} of its "
        f"{s.leg_length_mm:.0f} mm length at the largest load of {s.max_load_kn:.3g} kN",
        "a leg this soft has a mechanism in its load path: check joint and bearing preload"
        + (", air in the oil" if s.kind != "electric" else ", the drive's coupling"),
    )


def _per_length_grade(s: RobotScales, typical: float, source: str, check: str) -> Grade:
    high = 1000.0 * MAX_STATIC_STRAIN * s.leg_length_mm / (s.max_load_kn * s.stroke_range_mm / 1000.0)
    return Grade(
        (0.0, typical), (0.0, high), source,
        "the compliance only softens a leg (>= 0), and the sag at full stroke and the largest load stays below "
        f"{MAX_STATIC_STRAIN:.0%} of the leg length",
        check,
    )


def _oil_grade(s: RobotScales) -> Grade:
    return _per_length_grade(s, TYPICAL_OIL_UM_PER_KN_M,
                             f"an oil column of 25 mm bore or more with 1 GPa effective bulk modulus: up to "
                             f"{TYPICAL_OIL_UM_PER_KN_M:.0f} µm/(kN m)",
                             "an oil column this soft holds air or a soft hose: bleed the cylinder, check the hoses")


def _drive_grade(s: RobotScales) -> Grade:
    return _per_length_grade(s, TYPICAL_DRIVE_UM_PER_KN_M,
                             f"a ball screw (~100) or a steel-cord toothed belt (~5000): up to "
                             f"{TYPICAL_DRIVE_UM_PER_KN_M:.0f} µm/(kN m) of free length",
                             "a drive this soft is slack: check the belt tension or the screw's fixed bearing")


def _scale_grade(s: RobotScales) -> Grade:
    check = {
        "motor_encoder": "check its configured mm per revolution (lead, pulley, gear ratio)",
        "linear": "check its transducer's configured gradient or range (magnetostrictive wire speed, LVDT gain)",
    }.get(s.transducer or "", "check its configured length per count (lead, ratio) or its transducer gradient")
    return Grade(
        (-TYPICAL_GAIN_PPM, TYPICAL_GAIN_PPM), (-MAX_GAIN_ERROR_PPM, MAX_GAIN_ERROR_PPM),
        f"a calibrated length reading is within ±{TYPICAL_GAIN_PPM:.0f} ppm (transducer gradient or gain, "
        "ball-screw lead class C10, belt pitch)",
        f"beyond ±{MAX_GAIN_ERROR_PPM / 1e4:.0f} % of its travel a reading is not a scale error: the machine would "
        "not reach its workspace",
        check,
    )


def _thermal_grade(s: RobotScales) -> Grade:
    lo, hi = ALPHA_RANGE_PPM_PER_K
    why = f"structural metals expand by {lo:g}-{hi:g} ppm/K (invar to aluminium, with margin)"
    return Grade((lo, hi), (lo, hi), why, why)


def _backlash_grade(s: RobotScales) -> Grade:
    typical = max(TYPICAL_BACKLASH_PER_MM * s.leg_length_mm, MIN_TYPICAL_BACKLASH_MM)
    bound = max(MAX_BACKLASH_FRACTION * s.stroke_range_mm, MIN_BACKLASH_BOUND_MM, typical)
    return Grade(
        (-typical, typical), (-bound, bound),
        f"precision joints have up to {typical:.3g} mm of play (about 0.05 mm per metre of leg)",
        f"play of at most {bound:.3g} mm ({MAX_BACKLASH_FRACTION:.1%} of the {s.stroke_range_mm:.0f} mm stroke "
        "range); the sign depends on where the transducer sits relative to the play, so both signs are physical",
        "play this large means worn joints or a loose transducer coupling",
    )


CANDIDATES: tuple[Candidate, ...] = (
    Candidate(
        "leg_compliance", "leg compliance under gravity", "um_per_kN",
        "the legs shorten under the platform's weight (axial compliance); the load on each leg changes with "
        "the pose, so the platform sags by different amounts across the workspace",
        "axial load (kN)", lambda ctx: per_leg_diagonal(-ctx.force_kn * 1e-3), _compliance_grade,
    ),
    Candidate(
        "sensor_scale", "leg-length transducer scale (gain) error", "ppm",
        "the leg-length readings are too long or too short in proportion to the stroke (a gain error)",
        "stroke (mm)", lambda ctx: per_leg_diagonal(-ctx.stroke_mm * 1e-6), _scale_grade,
    ),
    Candidate(
        "thermal_expansion", "thermal expansion of the legs", "ppm_per_K",
        "the legs grow with temperature, so the same reported length gives a longer leg as the machine warms",
        "temperature (°C)", _thermal, _thermal_grade, per_leg=False, applicable=_thermal_applicable,
    ),
    Candidate(
        "joint_backlash", "joint backlash (depends on the direction of the last leg motion)", "mm",
        "the leg length depends on the direction from which each leg approached the pose (play in the "
        "joints or the transducer coupling)",
        "direction of last motion", lambda ctx: per_leg_diagonal(0.5 * ctx.direction), _backlash_grade,
        applicable=_backlash_applicable, history=True,
    ),
    Candidate(
        "oil_column_compliance", "hydraulic oil-column compliance (grows with stroke)", "um_per_kN_m",
        "the hydraulic legs are softer when extended: the compressed oil column grows with the stroke, so "
        "the sag under load grows with leg extension",
        "axial load x stroke (kN m)", lambda ctx: per_leg_diagonal(-ctx.force_kn * ctx.stroke_mm * 1e-6),
        _oil_grade, kinds=("hydraulic",),
    ),
    Candidate(
        "drive_compliance", "electric drive compliance (grows with the free screw or belt length)", "um_per_kN_m",
        "the screw or belt between the fixed bearing and the nut stretches under the leg's load, more as the leg "
        "extends and its free length grows",
        "axial load x stroke (kN m)", lambda ctx: per_leg_diagonal(-ctx.force_kn * ctx.stroke_mm * 1e-6),
        _drive_grade, kinds=("electric",), same_signature_as="oil_column_compliance",
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
    typical = min(TYPICAL_ZERO_SHIFT_MM.get(scales.transducer, TYPICAL_ZERO_SHIFT_MM[None]), bound)
    grade = Grade(
        (-typical, typical), (-bound, bound),
        f"a {'re-homed motor encoder' if scales.transducer != 'linear' else 'length transducer'} keeps its zero "
        f"to {typical * 1000:.0f} µm between sessions",
        f"a zero shift stays within {MAX_ZERO_SHIFT_FRACTION:.0%} of the stroke range",
        "a zero this far off means the leg was homed on the wrong switch edge or its transducer mount moved",
    )
    return TermGroup(
        key=ZERO_SHIFT, kind=LIBRARY, effect=ZERO_SHIFT, title=ZERO_SHIFT_TITLE, names=names, phi=phi,
        physical_range=grade.range_for(len(names)),
        sentence="each leg's length reading jumped by a constant between sessions (the machine was re-homed, "
                 "or a transducer's zero shifted)", variable="session",
    )


def library_groups(ctx: EffectContext, robot: Robot) -> tuple[list[TermGroup], dict[str, str]]:
    """The library effects that can occur on this machine, bound to the fitted rows, and why the others are not
    tested (not this machine's kind, not testable on this recording, or the same signature as another)."""
    scales = RobotScales.of(robot, ctx)
    groups, untestable = [], {}
    for cand in CANDIDATES:
        if scales.kind is not None and scales.kind not in cand.kinds:
            untestable[cand.name] = f"the robot file declares {scales.kind} legs, which cannot have it"
            continue
        if scales.kind is None and cand.same_signature_as is not None:
            untestable[cand.name] = (f"the same signature as {cand.same_signature_as} (the robot file does not say "
                                     "whether the legs are hydraulic or electric)")
            continue
        reason = cand.applicable(ctx)
        if reason is None:
            groups.append(cand.bind(ctx, scales))
        else:
            untestable[cand.name] = reason
    shift = zero_shift_group(ctx, scales)
    if shift is not None:
        groups.append(shift)
    return groups, untestable
