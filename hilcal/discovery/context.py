"""What every leg sees at every row of a recording: stroke, load, joint angles, motion history, time, sessions.

The missing-physics candidates (`hilcal.discovery.physics`) and the generic discrepancy terms
(`hilcal.discovery.generic_terms`) are functions of these variables. Everything is computed from the recording and
the robot file alone: loads from statics with the robot's moving mass at the measured poses, joint angles from the
nominal geometry, the direction and size of each leg's last move from the row order (execution order).

A recording may hold several sessions (e.g. measure rows one day, verify rows the next): a new session
starts where the clock goes backwards or jumps by more than SESSION_GAP_S. The motion before the first
row of a session is unknown, so the direction and size of that row's last move are unknown (0 and NaN).
"""

from __future__ import annotations

from dataclasses import dataclass, fields, replace

import numpy as np

from hilcal.kinematics import Geometry, gravity_wrench, leg_forces, leg_vectors, split_pose
from hilcal.recording import FORCE_COLUMNS, SESSION_GAP_S, Recording, session_numbers
from hilcal.robot import Robot

DIRECTION_DEADBAND_MM = 1e-3
"""Leg moves smaller than this keep the previous direction of motion (transducer resolution)."""
TEMPERATURE_WINDOW = 7


def detect_sessions(time_s: np.ndarray, gap_s: float = SESSION_GAP_S) -> np.ndarray:
    """Session number (0, 1, ...) of every row in execution order (the recording format's rule)."""
    return session_numbers(time_s, gap_s)


def measured_forces_kn(rec: Recording) -> np.ndarray | None:
    """The recording's measured axial leg loads [N, 6] (kN, compression positive; NaN where a row has none), or
    None without the leg1_force_kn ... leg6_force_kn columns. Where a row has all six they replace the statics of
    the robot file's mass: a hydraulic machine's pressures know the payload and the moves' dynamics, the file does
    not."""
    if not all(name in rec.extra for name in FORCE_COLUMNS):
        return None
    columns = [rec.extra[name] for name in FORCE_COLUMNS]  # a column with empty cells is read as text
    return np.column_stack([c if c.dtype.kind == "f" else np.array([float(v) if str(v).strip() else np.nan
                                                                    for v in c]) for c in columns])


def smooth_temperature(temp_c: np.ndarray, window: int = TEMPERATURE_WINDOW) -> np.ndarray:
    """Local-linear smoothing over neighbouring rows (in execution order) of a noisy temperature reading.

    Legs are tons of steel: their temperature changes over minutes, so row-to-row scatter in temp_c is
    sensor noise, which would otherwise enter a thermal regressor (errors in variables).
    This is scipy.signal.savgol_filter(temp_c, window, 1, mode="interp") (tests/hilcal/test_context.py compares
    them): a straight line fitted to each window is its mean at the centre, and the first and last windows' lines
    are evaluated at the ends. It is written out because importing scipy.signal costs every run 0.4 s.
    """
    x = np.asarray(temp_c, dtype=float)
    n = len(x)
    if n < 5:
        return x
    width = min(window, n - (1 - n % 2))
    half = width // 2
    out = np.empty(n)
    out[half:n - half] = np.convolve(x, np.full(width, 1.0 / width), mode="valid")
    at = np.arange(width, dtype=float)
    for first, ends in ((0, at[:half]), (n - width, at[width - half:])):
        slope, intercept = np.polyfit(at, x[first:first + width], 1)
        out[first + ends.astype(int)] = intercept + slope * ends
    return out


def _joint_frames(directions: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two unit vectors [6, 3] perpendicular to each leg's reference direction [6, 3]."""
    up = np.where(np.abs(directions[:, 2:3]) < 0.9, [[0.0, 0.0, 1.0]], [[1.0, 0.0, 0.0]])
    e1 = np.cross(up, directions)
    e1 /= np.linalg.norm(e1, axis=1, keepdims=True)
    return e1, np.cross(directions, e1)


def joint_axes(robot: Robot) -> tuple[np.ndarray, np.ndarray]:
    """The two axes [6, 2, 3] per leg that `joint_angles` projects on: perpendicular to the leg's direction at the
    home pose, in the base frame (base joints) and in the platform frame (platform joints)."""
    geom = Geometry.nominal(robot)
    R0, t0 = split_pose(robot.home)
    _, _, u0 = leg_vectors(geom, R0, t0)
    return tuple(np.stack(_joint_frames(d0), axis=1) for d0 in (u0, u0 @ R0))  # type: ignore[return-value]


def joint_angles(robot: Robot, poses: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Leg direction at the base and at the platform joint, as two small angles (rad) from the home direction.

    Returns (base [N, 6, 2], platform [N, 6, 2]). At the base the leg direction u is taken in the base frame;
    at the platform in the platform frame (R^T u). Each is projected on two axes perpendicular to its
    direction at the home pose (`joint_axes`): what a spherical or universal joint turns through.
    """
    geom = Geometry.nominal(robot)
    R, t = split_pose(np.asarray(poses, dtype=float))
    _, _, u = leg_vectors(geom, R, t)
    v = np.einsum("nji,nkj->nki", R, u)
    return tuple(np.einsum("nkj,kaj->nka", d, axes)  # type: ignore[return-value]
                 for d, axes in zip((u, v), joint_axes(robot), strict=True))


def motion_history(legs_mm: np.ndarray, session: np.ndarray, cmd: np.ndarray | None = None
                   ) -> tuple[np.ndarray, np.ndarray]:
    """Direction (+1 extending, -1 retracting, 0 unknown) and size (mm, NaN unknown) of each leg's last move.

    The first row of every session has an unknown history. A leg that did not move (below the deadband)
    keeps the direction and size of its previous move. A row commanded to the same pose as the row before it
    (`cmd`, a pose measured again in a row) did not move either: the difference of its readings is their noise,
    which at a few µm would otherwise flip the direction at random (issue 40).
    """
    n = len(legs_mm)
    direction = np.zeros((n, 6))
    size = np.full((n, 6), np.nan)
    same_pose = np.zeros(n, dtype=bool)
    if cmd is not None:
        same_pose[1:] = np.all(np.asarray(cmd)[1:] == np.asarray(cmd)[:-1], axis=1)
    for k in range(1, n):
        if session[k] != session[k - 1]:
            continue
        step = legs_mm[k] - legs_mm[k - 1]
        moved = (np.abs(step) >= DIRECTION_DEADBAND_MM) & ~same_pose[k]
        direction[k] = np.where(moved, np.sign(step), direction[k - 1])
        size[k] = np.where(moved, np.abs(step), size[k - 1])
    return direction, size


@dataclass(frozen=True)
class EffectContext:
    """Per-row variables of a recording (rows in execution order; [N, 6] arrays are per leg)."""

    legs_mm: np.ndarray
    stroke_mm: np.ndarray
    force_kn: np.ndarray
    direction: np.ndarray
    move_mm: np.ndarray
    base_angle_rad: np.ndarray
    platform_angle_rad: np.ndarray
    temp_c: np.ndarray | None
    time_s: np.ndarray
    session: np.ndarray
    session_time_s: np.ndarray
    pose: np.ndarray

    @classmethod
    def from_recording(cls, rec: Recording, robot: Robot) -> EffectContext:
        """Loads from statics at the measured poses; motion history from the row order, per session."""
        nominal = Geometry.nominal(robot)
        force = leg_forces(nominal, rec.meas, gravity_wrench(robot, rec.meas)) / 1000.0
        measured = measured_forces_kn(rec)
        if measured is not None:
            rows = np.all(np.isfinite(measured), axis=1)
            force[rows] = measured[rows]
        session = detect_sessions(rec.time_s)
        direction, move = motion_history(rec.legs_mm, session, rec.cmd)
        base, platform = joint_angles(robot, rec.meas)
        start = np.array([rec.time_s[session == s].min() for s in session])
        temp = None
        if rec.temp_c is not None:
            temp = np.asarray(rec.temp_c, dtype=float).copy()
            for s in np.unique(session):
                rows = session == s
                temp[rows] = smooth_temperature(temp[rows])
        return cls(
            legs_mm=rec.legs_mm, stroke_mm=rec.legs_mm - robot.l0, force_kn=force, direction=direction,
            move_mm=move, base_angle_rad=base, platform_angle_rad=platform, temp_c=temp, time_s=rec.time_s,
            session=session, session_time_s=rec.time_s - start, pose=rec.meas,
        )

    @classmethod
    def at_poses(cls, robot: Robot, poses: np.ndarray) -> EffectContext:
        """The pose-determined variables at planned poses (legs by nominal inverse kinematics; no history)."""
        q = np.atleast_2d(np.asarray(poses, dtype=float))
        nominal = Geometry.nominal(robot)
        R, t = split_pose(q)
        _, legs, _ = leg_vectors(nominal, R, t)
        base, platform = joint_angles(robot, q)
        n = len(q)
        return cls(
            legs_mm=legs, stroke_mm=legs - robot.l0,
            force_kn=leg_forces(nominal, q, gravity_wrench(robot, q)) / 1000.0, direction=np.zeros((n, 6)),
            move_mm=np.full((n, 6), np.nan), base_angle_rad=base, platform_angle_rad=platform, temp_c=None,
            time_s=np.zeros(n), session=np.zeros(n, dtype=int), session_time_s=np.zeros(n), pose=q,
        )

    def at_recorded_state(self, recorded: EffectContext) -> EffectContext:
        """These (planned) rows with the recording's median temperature: extra poses taken at today's state."""
        if recorded.temp_c is None:
            return self
        return replace(self, temp_c=np.full(self.n, float(np.median(recorded.temp_c))))

    @property
    def n(self) -> int:
        return int(self.legs_mm.shape[0])

    def rows(self, mask: np.ndarray) -> EffectContext:
        """The same variables for a subset of rows (history stays as computed on the whole recording)."""
        values = {}
        for f in fields(self):
            value = getattr(self, f.name)
            values[f.name] = None if value is None else value[mask]
        return EffectContext(**values)

    def unknown_history(self) -> np.ndarray:
        """[N, 6] legs whose direction of approach is unknown (no recorded move since their session started)."""
        return self.direction == 0

    def per_leg(self, values: np.ndarray) -> np.ndarray:
        """Broadcast a per-row quantity [N] to [N, 6]."""
        return np.broadcast_to(np.asarray(values, dtype=float)[:, None], self.legs_mm.shape)
