"""Leg wiring: do the logged leg readings follow the legs of the robot file, in its order and direction?

A set-up fault that no error model fits: the logger's leg 2 is the robot file's leg 3 (cables, a logger map, or
another numbering of the same machine), or a transducer counts down as its leg extends. The measured poses give,
with the nominal geometry, the length each leg must have had; every reading column is regressed on every leg's
length (offset and slope), and the assignment of columns to legs with the least total misfit
(``scipy.optimize.linear_sum_assignment``) is compared with the order as given. The geometric errors leave the
right column a misfit of a fraction of a mm; a wrong one is off by a good part of the stroke.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.optimize import linear_sum_assignment

from hilcal.kinematics import Geometry, inverse_kinematics
from hilcal.robot import Robot

MISFIT_RATIO = 5.0
"""A column is taken for another leg only when the leg as given fits it this many times worse."""
MIN_MISFIT_FRACTION = 0.01
"""... and the misfit as given is at least this share of the leg's recorded length range."""
MIN_RANGE_MM = 0.5
"""Legs that moved less than this across the recording cannot be told apart."""
MIN_R2 = 0.9
"""A reading that explains less of its best leg's variation than this follows no leg (dead, or not a leg)."""


@dataclass(frozen=True)
class LegWiring:
    """For robot leg i (0-based): the reading column that follows it, the reading's slope per mm of the leg, the
    misfit (mm of leg) of that column and of the column as given, and the columns that follow no leg at all."""

    column_of_leg: np.ndarray
    slope: np.ndarray
    misfit_mm: np.ndarray
    misfit_as_given_mm: np.ndarray
    dead: tuple[int, ...]
    checked: bool
    mirror_mm: np.ndarray
    """Per leg: the sum reading + length, for a reading that counts the wrong way (the leg is mirror - reading)."""

    @property
    def reordered(self) -> bool:
        return bool(self.checked and np.any(self.column_of_leg != np.arange(6)))

    @property
    def reversed_legs(self) -> tuple[int, ...]:
        """Robot legs (1-based) whose reading counts down as the leg extends."""
        return tuple(int(i) + 1 for i in np.flatnonzero(self.slope < 0)) if self.checked else ()

    @property
    def problem(self) -> bool:
        return self.reordered or bool(self.reversed_legs) or bool(self.dead)

    def sentence(self, column_names: list[str] | None = None) -> str:
        """What is wrong, in the machine's terms, and what to change."""
        def name(j: int) -> str:
            return f"'{column_names[j]}'" if column_names else f"reading {j + 1}"

        parts = []
        if self.reordered:
            moved = [i for i in range(6) if self.column_of_leg[i] != i]
            pairs = ", ".join(f"leg {i + 1} is {name(int(self.column_of_leg[i]))} (misfit "
                              f"{self.misfit_mm[i]:.3g} mm, against {self.misfit_as_given_mm[i]:.3g} mm as given)"
                              for i in moved)
            parts.append(f"the leg readings are not in the robot file's order: {pairs}; check the logger's leg "
                         "order, the cabling, or the robot file's leg numbering")
        if self.reversed_legs:
            mirrored = ", ".join(f"leg {leg} = {self.mirror_mm[leg - 1]:.3f} mm - reading"
                                 for leg in self.reversed_legs)
            parts.append(f"leg(s) {', '.join(map(str, self.reversed_legs))} read(s) less as the leg extends: the "
                         "transducer counts the wrong way (direction sign in the controller or logger); read here as "
                         f"{mirrored} (fitted to the nominal geometry, so that leg's zero is not judged: fix the sign "
                         "and run again for it)")
        if self.dead:
            parts.append(f"{', '.join(name(j) for j in self.dead)} follow(s) no leg (R² below {MIN_R2:g} against "
                         "every leg): a dead transducer, or a column that is not a leg length")
        return "; ".join(parts)

    def corrected(self, legs_mm: np.ndarray) -> np.ndarray:
        """Leg lengths in the robot file's order; a reversed reading mirrored about its fitted offset (slope -1, so a
        scale error stays for the diagnosis)."""
        out = np.asarray(legs_mm, dtype=float)[:, self.column_of_leg].copy()
        for leg in self.reversed_legs:
            out[:, leg - 1] = self.mirror_mm[leg - 1] - out[:, leg - 1]
        return out

    def to_json(self) -> dict[str, object]:
        return {
            "checked": self.checked, "problem": self.problem, "column_of_leg": (self.column_of_leg + 1).tolist(),
            "slope": self.slope.tolist(), "misfit_mm": self.misfit_mm.tolist(),
            "misfit_as_given_mm": self.misfit_as_given_mm.tolist(), "reversed_legs": list(self.reversed_legs),
            "dead_columns": [j + 1 for j in self.dead], "sentence": self.sentence() if self.problem else "",
            "mirror_mm": [float(m) if i + 1 in self.reversed_legs else None for i, m in enumerate(self.mirror_mm)],
            "rule": "leg i's length is reading column_of_leg[i]; for a reversed leg, mirror_mm[i] - that reading",
        }


def check_wiring(legs_mm: np.ndarray, meas: np.ndarray, robot: Robot) -> LegWiring:
    """Compare reading columns (n, 6) with the leg lengths the measured poses (n, 6: mm, deg) imply."""
    readings = np.asarray(legs_mm, dtype=float)
    implied = inverse_kinematics(Geometry.nominal(robot), np.asarray(meas, dtype=float))
    ok = np.all(np.isfinite(readings), axis=1) & np.all(np.isfinite(implied), axis=1)
    readings, implied = readings[ok], implied[ok]
    identity = np.arange(6)
    if len(readings) < 8 or np.any(np.ptp(implied, axis=0) < MIN_RANGE_MM):
        nan = np.full(6, np.nan)
        return LegWiring(identity, np.ones(6), nan, nan, (), False, nan)
    centred_l = implied - implied.mean(axis=0)
    centred_r = readings - readings.mean(axis=0)
    ss_l = np.sum(centred_l**2, axis=0)
    slope = (centred_r.T @ centred_l) / ss_l[None, :]
    rss = np.sum(centred_r**2, axis=0)[:, None] - slope**2 * ss_l[None, :]
    misfit = np.sqrt(np.clip(rss, 0.0, None) / len(readings)) / np.maximum(np.abs(slope), 1e-12)
    cols, legs = linear_sum_assignment(misfit)
    column_of_leg = np.empty(6, dtype=int)
    column_of_leg[legs] = cols
    as_given = np.diag(misfit).copy()
    assigned = misfit[column_of_leg, identity]
    span = np.ptp(implied, axis=0)
    moved = (column_of_leg != identity) & (as_given > MISFIT_RATIO * assigned) & (as_given > MIN_MISFIT_FRACTION * span)
    column_of_leg = np.where(moved, column_of_leg, identity)
    if len(set(column_of_leg.tolist())) < 6:
        column_of_leg = identity
    chosen_slope = slope[column_of_leg, identity]
    r2 = 1.0 - np.clip(rss, 0.0, None) / np.maximum(np.sum(centred_r**2, axis=0)[:, None], 1e-300)
    dead = tuple(int(j) for j in range(6) if np.max(r2[j]) < MIN_R2)
    mirror = np.where(chosen_slope < 0, np.mean(readings[:, column_of_leg] + implied, axis=0), np.nan)
    return LegWiring(column_of_leg, chosen_slope, misfit[column_of_leg, identity], as_given, dead, True, mirror)
