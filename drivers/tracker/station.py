"""A laser tracker's stations during a run: every pose registers the base monuments, and a registration far from the
previous pose's means the tracker was set up again (moved for the line of sight, knocked, or between days).

A station is where the tracker stands, its frame T_tracker<-base. Two registrations from one station differ only by
their noise: each monument's registered position in the tracker's frame scatters by about u = U/2 per coordinate,
U(d) = constant + per_m · d the tracker's MPE at the monument's distance (read as k = 2), a little less for the
registration's averaging; the difference of two registrations, about √2 u per coordinate, so its largest monument
displacement stays below 2-3 U. ``MOVE_THRESHOLD_MPE`` times U at the farthest monument (0.70 mm at the simulated
station, whose farthest monument is 9.2 m away) is then far beyond the noise (about 14 standard deviations of a
coordinate) and far below any set-up again by hand (centimetres): a larger displacement starts a new station.

``StationLog`` counts the stations (1 for the first pose; a resumed run continues from the journal's last row) and
says each change: how far the tracker's origin moved and its frame turned, in the base frame, and the largest
displacement of a monument in the tracker's view.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np
from scipy.spatial.transform import Rotation

MOVE_THRESHOLD_MPE = 10.0
"""A registration whose monuments moved by more than this many MPEs (at the farthest monument) from the previous
pose's is a new station."""


def station_pose(alignment: np.ndarray) -> np.ndarray:
    """Where the tracker stands, from T_tracker<-base (4x4): [x, y, z mm, roll, pitch, yaw deg] of its frame in the
    base frame (p_base = R p_tracker + t, R = Rz(yaw) Ry(pitch) Rx(roll))."""
    T = np.asarray(alignment, dtype=float)
    R = T[:3, :3].T
    yaw, pitch, roll = Rotation.from_matrix(R).as_euler("ZYX", degrees=True)
    return np.array([*(-R @ T[:3, 3]), roll, pitch, yaw])


def alignment_of(pose: np.ndarray) -> np.ndarray:
    """T_tracker<-base (4x4) of a station pose [x, y, z mm, roll, pitch, yaw deg] (the inverse of ``station_pose``)."""
    p = np.asarray(pose, dtype=float)
    R = Rotation.from_euler("ZYX", p[[5, 4, 3]], degrees=True).as_matrix()
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R.T, -R.T @ p[:3]
    return T


def mpe_mm(distance_mm: np.ndarray, constant_um: float, per_m_um: float) -> np.ndarray:
    """U(d) = constant + per_m · d, mm."""
    return (constant_um + per_m_um * np.asarray(distance_mm, dtype=float) / 1000.0) / 1000.0


@dataclass(frozen=True)
class StationChange:
    """The tracker found set up again: the new station's number and how it moved from the previous pose's."""

    station: int
    moved_mm: float
    """How far the tracker's origin moved, in the base frame."""
    turned_deg: float
    """How far its frame turned."""
    monument_shift_mm: float
    """The largest displacement of a base monument in the tracker's view (what its searches met)."""
    threshold_mm: float
    """The displacement beyond which a registration is a new station (``MOVE_THRESHOLD_MPE`` MPEs)."""

    def to_json(self) -> dict[str, float | int]:
        return {k: (round(v, 4) if isinstance(v, float) else v) for k, v in asdict(self).items()}


class StationLog:
    """The stations of one run's tracker: compares every registration with the previous pose's."""

    def __init__(self, monuments_mm: np.ndarray, mpe_constant_um: float, mpe_per_m_um: float) -> None:
        self.monuments = np.asarray(monuments_mm, dtype=float)
        self.mpe = (float(mpe_constant_um), float(mpe_per_m_um))
        self.number = 0
        """The current station (0 before the first pose)."""
        self.last: np.ndarray | None = None
        """The previous pose's registration T_tracker<-base."""

    def resume(self, number: int, pose: np.ndarray) -> None:
        """Continue a run whose last journaled pose was measured from station ``number``, registered at ``pose``."""
        self.number, self.last = int(number), alignment_of(pose)

    def threshold_mm(self, alignment: np.ndarray) -> float:
        """``MOVE_THRESHOLD_MPE`` times the MPE at the monument farthest from the tracker."""
        seen = self.monuments @ np.asarray(alignment, dtype=float)[:3, :3].T + np.asarray(alignment)[:3, 3]
        return MOVE_THRESHOLD_MPE * float(np.max(mpe_mm(np.linalg.norm(seen, axis=1), *self.mpe)))

    def observe(self, alignment: np.ndarray) -> StationChange | None:
        """A pose's registration: the change when it starts a new station, else None (the first pose: station 1)."""
        T = np.asarray(alignment, dtype=float)
        previous, self.last = self.last, T
        if previous is None:
            self.number = max(self.number, 1)
            return None
        shift = float(np.max(np.linalg.norm((T - previous)[:3, :3] @ self.monuments.T
                                            + (T - previous)[:3, 3:4], axis=0)))
        threshold = self.threshold_mm(T)
        if shift <= threshold:
            return None
        self.number += 1
        before, after = station_pose(previous), station_pose(T)
        turn = Rotation.from_matrix(T[:3, :3].T @ previous[:3, :3]).magnitude()
        return StationChange(self.number, float(np.linalg.norm(after[:3] - before[:3])), float(np.degrees(turn)),
                             shift, threshold)


def stations_summary(rows: list[dict]) -> dict | None:
    """report.json's ``stations`` from a run's journaled rows in measuring order (each ``detail`` with its ``station``
    and, on a new station's first row, its ``station_change``): how many stations and after which poses the tracker
    was set up again; None when no row says a station (a CMM run)."""
    numbered = [r for r in rows if isinstance(r.get("detail", {}).get("station"), int)]
    if not numbered:
        return None
    moves = []
    for k, row in enumerate(rows):
        change = row["detail"].get("station_change")
        if change is None:
            continue
        before = rows[k - 1] if k else None
        moves.append({**change, "first_pose": _pose_name(row), "after_pose": None if before is None else
                      _pose_name(before), "after_rows": k})
    return {"count": max(r["detail"]["station"] for r in numbered), "moves": moves,
            "threshold": f"a registration whose monuments moved by more than {MOVE_THRESHOLD_MPE:g} MPEs (at the "
                         "farthest monument) from the previous pose's starts a new station",
            "recording_station_column": False,
            "frames": "every pose registered the base monuments itself, so every row is in the base frame: the "
                      "recording has no station column (a free frame per station would throw the monuments away)"}


def _pose_name(row: dict) -> str:
    return f"{row['phase'].replace('_', ' ')} pose {int(row['index']) + 1}"
