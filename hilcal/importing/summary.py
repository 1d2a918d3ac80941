"""What an import brought in, per session: rows, files, time span, leg and pose ranges, readings at a leg's extreme.

Sessions are those `hilcal diagnose` will see (``hilcal.recording.session_numbers``). A reading "at a leg's
extreme" lies within EXTREME_FRACTION of the stroke from the robot's leg limits, or beyond them: an end stop,
a saturated transducer or a wrong zero; it needs a robot file.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from hilcal.recording import Recording, session_numbers
from hilcal.robot import Robot

EXTREME_FRACTION = 0.01
"""A reading within 1 % of the stroke from a leg limit sits at that leg's extreme."""


@dataclass(frozen=True)
class SessionSummary:
    """One session of an imported recording."""

    index: int
    files: tuple[str, ...]
    n_rows: int
    n_measure: int
    n_verify: int
    time_span_s: float
    legs_min_mm: np.ndarray
    legs_max_mm: np.ndarray
    pose_min: np.ndarray
    """(6,) smallest [x, y, z mm, roll, pitch, yaw deg] of the measured poses."""
    pose_max: np.ndarray
    at_extreme: np.ndarray | None
    """(6,) readings per leg at that leg's extreme; None without a robot file."""

    def to_json(self) -> dict[str, Any]:
        return {
            "session": self.index, "files": list(self.files), "rows": self.n_rows, "measure": self.n_measure,
            "verify": self.n_verify, "time_span_s": self.time_span_s,
            "legs_min_mm": self.legs_min_mm.tolist(), "legs_max_mm": self.legs_max_mm.tolist(),
            "pose_min": self.pose_min.tolist(), "pose_max": self.pose_max.tolist(),
            "at_extreme": None if self.at_extreme is None else self.at_extreme.tolist(),
        }


def at_extreme(legs_mm: np.ndarray, robot: Robot) -> np.ndarray:
    """(n, 6) True where a reading lies within EXTREME_FRACTION of the stroke from a leg limit, or beyond it."""
    lo, hi = robot.leg_limits
    band = EXTREME_FRACTION * (hi - lo)
    return (legs_mm <= lo + band) | (legs_mm >= hi - band)


def summarise(rec: Recording, file_of_row: np.ndarray, robot: Robot | None) -> tuple[SessionSummary, ...]:
    """One SessionSummary per session of the recording; ``file_of_row`` names each row's file."""
    session = session_numbers(rec.time_s)
    extreme = None if robot is None else at_extreme(rec.legs_mm, robot)
    out = []
    for s in np.unique(session):
        rows = session == s
        files = tuple(dict.fromkeys(str(f) for f in file_of_row[rows]))
        out.append(SessionSummary(
            index=int(s) + 1,
            files=files,
            n_rows=int(rows.sum()),
            n_measure=int(np.sum(rec.phase[rows] == "measure")),
            n_verify=int(np.sum(rec.phase[rows] == "verify")),
            time_span_s=float(np.ptp(rec.time_s[rows])),
            legs_min_mm=rec.legs_mm[rows].min(axis=0),
            legs_max_mm=rec.legs_mm[rows].max(axis=0),
            pose_min=rec.meas[rows].min(axis=0),
            pose_max=rec.meas[rows].max(axis=0),
            at_extreme=None if extreme is None else extreme[rows].sum(axis=0),
        ))
    return tuple(out)
