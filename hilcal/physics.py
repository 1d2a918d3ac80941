"""Candidate physics that a rigid geometric model leaves out, each a small model linear in its parameters.

Every candidate adds a correction to the geometric length of each leg:
    geometric length = reported length + dl0 + phi(pose, load, temperature, history) @ theta,
where phi [N, 6, q] is computed from the recording and theta holds the candidate's parameters in the
units given. The constant part of any correction is absorbed by dl0, so only its variation over the
poses can be seen.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from scipy.signal import savgol_filter

from hilcal.kinematics import N_LEGS, Geometry, gravity_wrench, inverse_kinematics, leg_forces
from hilcal.recording import Recording
from hilcal.robot import Robot

MIN_TEMPERATURE_RANGE_K = 0.2
TEMPERATURE_WINDOW = 7
REFERENCE_TEMPERATURE_C = 20.0
"""ISO 1 reference temperature: the nominal geometry is taken to hold at 20 °C."""


@dataclass(frozen=True)
class EffectContext:
    """What the candidates may depend on, for every row of a recording, in execution order."""

    legs_mm: np.ndarray
    stroke_mm: np.ndarray
    force_kn: np.ndarray
    direction: np.ndarray
    temp_c: np.ndarray | None
    time_s: np.ndarray

    @classmethod
    def from_recording(cls, rec: Recording, robot: Robot) -> EffectContext:
        """Axial gravity loads from statics at the measured poses; motion direction from the row order.

        The run is assumed to start at the robot's home pose, so the first row's direction is that of
        the move from home.
        """
        nominal = Geometry.nominal(robot)
        force = leg_forces(nominal, rec.meas, gravity_wrench(robot, rec.meas)) / 1000.0
        previous = np.vstack([inverse_kinematics(nominal, robot.home)[None, :], rec.legs_mm[:-1]])
        step = rec.legs_mm - previous
        direction = np.sign(step)
        for k in range(len(direction)):
            still = np.abs(step[k]) < 1e-3
            direction[k, still] = direction[k - 1, still] if k else 1.0
        return cls(
            legs_mm=rec.legs_mm, stroke_mm=rec.legs_mm - robot.l0, force_kn=force, direction=direction,
            temp_c=None if rec.temp_c is None else smooth_temperature(rec.temp_c), time_s=rec.time_s,
        )

    def rows(self, mask: np.ndarray) -> EffectContext:
        return EffectContext(
            legs_mm=self.legs_mm[mask], stroke_mm=self.stroke_mm[mask], force_kn=self.force_kn[mask],
            direction=self.direction[mask], temp_c=None if self.temp_c is None else self.temp_c[mask],
            time_s=self.time_s[mask],
        )


def smooth_temperature(temp_c: np.ndarray, window: int = TEMPERATURE_WINDOW) -> np.ndarray:
    """Local-linear smoothing over neighbouring rows (in execution order) of a noisy temperature reading.

    Hydraulic legs are tons of steel: their temperature changes over minutes, so row-to-row scatter in
    temp_c is sensor noise, which would otherwise enter the thermal regressor (errors in variables).
    """
    n = len(temp_c)
    if n < 5:
        return np.asarray(temp_c, dtype=float)
    return savgol_filter(np.asarray(temp_c, dtype=float), min(window, n - (1 - n % 2)), 1, mode="interp")


def _per_leg(values: np.ndarray) -> np.ndarray:
    """[N, 6] leg-wise regressor -> [N, 6, 6] with one parameter per leg."""
    out = np.zeros((*values.shape, N_LEGS))
    for i in range(N_LEGS):
        out[:, i, i] = values[:, i]
    return out


@dataclass(frozen=True)
class Candidate:
    """A documented physical effect: its parameters, units, regressors and the sentence that names it."""

    name: str
    title: str
    unit: str
    per_leg: bool
    sentence: str
    regressor: Callable[[EffectContext], np.ndarray]
    applicable: Callable[[EffectContext], str | None] = lambda ctx: None

    def parameter_names(self) -> tuple[str, ...]:
        if self.per_leg:
            return tuple(f"leg{i + 1}_{self.name}_{self.unit}" for i in range(N_LEGS))
        return (f"{self.name}_{self.unit}",)


def _thermal_applicable(ctx: EffectContext) -> str | None:
    if ctx.temp_c is None:
        return "no temp_c column in the recording"
    span = float(np.ptp(ctx.temp_c))
    if span < MIN_TEMPERATURE_RANGE_K:
        return f"temperature varied only {span:.2f} K; leg growth cannot be told from a transducer scale error"
    return None


def _thermal(ctx: EffectContext) -> np.ndarray:
    """Leg growth alpha * L * (T - 20 °C): a drift over the run plus a scale-like offset, one parameter."""
    dt = ctx.temp_c - REFERENCE_TEMPERATURE_C
    return (ctx.legs_mm * dt[:, None] * 1e-6)[:, :, None]


def _backlash_applicable(ctx: EffectContext) -> str | None:
    if np.all(ctx.direction == ctx.direction[0]):
        return "every pose was approached from the same direction, so backlash is constant and absorbed by dl0"
    return None


CANDIDATES: tuple[Candidate, ...] = (
    Candidate(
        "leg_compliance", "leg compliance under gravity", "um_per_kN", True,
        "the legs shorten under the platform's weight (axial compliance); the load on each leg changes with "
        "the pose, so the platform sags by different amounts across the workspace",
        lambda ctx: _per_leg(-ctx.force_kn * 1e-3),
    ),
    Candidate(
        "sensor_scale", "leg-length transducer scale (gain) error", "ppm", True,
        "the leg-length transducers over- or under-read in proportion to the stroke (a gain error)",
        lambda ctx: _per_leg(-ctx.stroke_mm * 1e-6),
    ),
    Candidate(
        "thermal_expansion", "thermal expansion of the legs", "ppm_per_K", False,
        "the legs grow with temperature, so the same reported length gives a longer leg as the machine warms",
        _thermal, _thermal_applicable,
    ),
    Candidate(
        "joint_backlash", "joint backlash (depends on the direction of the last leg motion)", "mm", True,
        "the leg length depends on the direction from which each leg approached the pose (play in the "
        "joints or the transducer coupling)",
        lambda ctx: _per_leg(0.5 * ctx.direction), _backlash_applicable,
    ),
    Candidate(
        "oil_column_compliance", "hydraulic oil-column compliance (grows with stroke)", "um_per_kN_m", True,
        "the hydraulic legs are softer when extended: the compressed oil column grows with the stroke, so "
        "the sag under load grows with leg extension",
        lambda ctx: _per_leg(-ctx.force_kn * ctx.stroke_mm * 1e-6),
    ),
)

CANDIDATES_BY_NAME = {c.name: c for c in CANDIDATES}
