"""Recordings as another simulator makes them, for the coverage study: noisy leg readings, a sphere-fit column in
another convention, a repeated pose.

Why: hilcal's rig reports exactly the lengths it moved to, and its `sphere_fit_rms_mm` column follows hilcal's own
registration, so the noise yardstick built from that column is right by construction. A recording made elsewhere
(issue 40: another simulator's 50 recordings, 90.4 % within 2 standard errors) has readings with noise of their own,
rounded as an encoder rounds them, and a column whose relation to the sphere noise is another's convention. Here the
rig's recording is post-processed into that: every leg reading gets Gaussian noise and is rounded to the encoder's
step, the column is scaled, and the plan measures one pose four times in a row, as hilcal's plan does
(`procedures.plan.REPEATS`).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np

from hilcal.kinematics import Geometry
from hilcal.planning.machine_time import MotionRules, repeatable_pose
from hilcal.recording import Recording
from hilcal.robot import Robot

REPEATS = 3
"""Extra measurements of the repeated pose (measured 4 times in a row, as hilcal's plan)."""
LEG_SIGMA_UM = (0.5, 1.0, 1.5, 2.0)
"""Leg-reading noise (µm, one standard deviation), taken in turn by the seeds of a kind."""
LEG_STEP_UM = (1.0, 0.5)
"""Encoder steps (µm) the noisy readings are rounded to, taken in turn."""
CMM_NOISE_MM = (0.005, 0.002)
"""Sphere-centre noise of the CMM (mm), taken in turn: at 2 µm the readings' noise is a good part of the whole."""


@dataclass(frozen=True)
class Readings:
    """How a recording's readings and column differ from hilcal's rig."""

    leg_sigma_um: float = 0.0
    """Gaussian noise on every leg reading (µm); 0 with `step_um` 0: the rig's readings as they are."""
    step_um: float = 0.0
    """The encoder step the readings are rounded to (µm); 0: the rig's own rounding (1 µm, no error)."""
    column_factor: float = 1.0
    """The `sphere_fit_rms_mm` column states this times what hilcal's registration gives."""
    cmm_noise_mm: float = 0.005
    repeats: int = 0
    """Extra measurements of the repeated pose."""

    @property
    def plain(self) -> bool:
        return self == Readings()

    def label(self) -> str:
        parts = []
        if self.step_um:
            parts.append(f"readings {self.leg_sigma_um:g} µm noise, {self.step_um:g} µm steps")
        if self.column_factor != 1.0:
            parts.append(f"column {self.column_factor:g}x")
        if self.cmm_noise_mm != 0.005:
            parts.append(f"CMM {self.cmm_noise_mm * 1000:g} µm")
        return ", ".join(parts)


def readings_for(k: int, column_factor: float) -> Readings:
    """The k-th recording's readings of a kind: the CMM noise alternates, the readings' noise changes every second
    seed and the step with the sum of both indices, so eight seeds give every noise level with both CMMs and both
    steps, and every CMM with both steps twice."""
    cmm, sigma = k % len(CMM_NOISE_MM), (k // len(CMM_NOISE_MM)) % len(LEG_SIGMA_UM)
    return Readings(LEG_SIGMA_UM[sigma], LEG_STEP_UM[(cmm + sigma) % len(LEG_STEP_UM)], column_factor,
                    CMM_NOISE_MM[cmm], REPEATS)


def with_repeats(robot: Robot, measure: np.ndarray, repeats: int) -> np.ndarray:
    """The measure poses with the one that has most room below it for a repeat's retreat measured `repeats` more
    times right after itself (``hilcal.planning.machine_time.repeatable_pose``, as the plan chooses it)."""
    if not repeats:
        return measure
    k = repeatable_pose(Geometry.nominal(robot), measure, robot.leg_limits[0], MotionRules())
    return np.insert(measure, [k + 1] * repeats, measure[k], axis=0)


def as_read(rec: Recording, readings: Readings, seed: int) -> Recording:
    """The rig's recording as another machine would have recorded it: noisy readings rounded to the encoder's step
    (the rig moved to the lengths before the noise, so the noise is the readings' error), the column scaled."""
    legs = rec.legs_mm
    if readings.step_um:
        rng = np.random.default_rng([seed, 0x1E6])
        step = readings.step_um / 1000.0
        legs = np.round((legs + rng.normal(0.0, readings.leg_sigma_um / 1000.0, legs.shape)) / step) * step
    extra = dict(rec.extra)
    if readings.column_factor != 1.0:
        extra["sphere_fit_rms_mm"] = extra["sphere_fit_rms_mm"] * readings.column_factor
    return dataclasses.replace(rec, legs_mm=legs, extra=extra)
