"""Unit and orientation conversions into the recording's mm and degrees, with the checks that a unit fits the values.

Poses come out as [x, y, z mm, roll, pitch, yaw deg] with R = Rz(yaw) Ry(pitch) Rx(roll), R mapping platform
vectors into the base frame (docs/model.md). Quaternions are Hamilton quaternions of that same R (as written by
ROS, Eigen and scipy). A problem is raised as a ValueProblem at (row, column of the group) for the importer to
name the file, line and column.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from hilcal.importing.errors import ValueProblem
from hilcal.importing.mapping import LegsMap
from hilcal.pose_measurement import pose_from_matrix
from hilcal.recording import ANGLE_MARGIN_DEG, LEG_MARGIN_MM, POSITION_MARGIN_MM
from hilcal.robot import Robot

QUATERNION_NORM_TOLERANCE = 1e-3
"""|norm - 1| above this is not rounding: the columns are not a unit quaternion (or not this kind)."""
MATRIX_TOLERANCE = 1e-3
"""Largest |R^T R - I| entry of a rotation matrix written with a few digits."""
MAX_LEG_RATIO = 3.0
"""Without a robot file: a leg's longest reading is at most this times its shortest. A leg's retracted length holds
its stroke (cylinder body, screw, guide), so a ratio above 2 is rare and above 3 means a unit or zero is wrong."""
AXES = ("x_mm", "y_mm", "z_mm", "roll_deg", "pitch_deg", "yaw_deg")
MM_PER_UNIT = {"mm": 1.0, "m": 1000.0, "in": 25.4}


def legs_mm(readings: np.ndarray, legs: LegsMap) -> np.ndarray:
    """(n, 6) leg lengths in mm from readings in the map's unit: zero_mm + mm_per_unit * reading."""
    return legs.zero() + legs.scale_mm() * np.asarray(readings, dtype=float)


def check_legs(lengths_mm: np.ndarray, readings: np.ndarray, legs: LegsMap, robot: Robot | None) -> None:
    """Lengths within the robot's leg limits widened by the recording's margin; without a robot, positive and
    each leg's longest at most MAX_LEG_RATIO times its shortest."""
    lo, hi = (0.0, np.inf) if robot is None else (robot.leg_limits[0] - LEG_MARGIN_MM,
                                                  robot.leg_limits[1] + LEG_MARGIN_MM)
    bad = (lengths_mm <= 0.0) | (lengths_mm < lo) | (lengths_mm > hi)
    if robot is None and not np.any(bad):
        ratio = lengths_mm.max(axis=0) / lengths_mm.min(axis=0)
        if np.any(ratio > MAX_LEG_RATIO):
            k = int(np.argmax(ratio))
            i = int(np.argmin(lengths_mm[:, k]))
            raise ValueProblem(i, k, f"{_how(readings, lengths_mm, legs, i, k)}, while this leg reaches "
                               f"{lengths_mm[:, k].max():.6g} mm elsewhere: more than {MAX_LEG_RATIO:g} times its "
                               "shortest length, which no leg's stroke allows: check unit, mm_per_unit and zero_mm "
                               "in [legs] (or give the robot file)")
    if not np.any(bad):
        return
    i, k = (int(v) for v in np.argwhere(bad)[0])
    how = _how(readings, lengths_mm, legs, i, k)
    if robot is None:
        raise ValueProblem(i, k, f"{how} is not a positive leg length: check unit, mm_per_unit and zero_mm")
    raise ValueProblem(
        i, k, f"{how}, outside the robot's leg limits widened by {LEG_MARGIN_MM:g} mm [{lo:g}, {hi:g}] mm: "
        "check unit, mm_per_unit and zero_mm in [legs]")


def _how(readings: np.ndarray, lengths_mm: np.ndarray, legs: LegsMap, i: int, k: int) -> str:
    scale = "" if legs.unit in MM_PER_UNIT else f" x {legs.scale_mm()[k]:g} mm/{legs.unit}"
    return f"reading {readings[i, k]:g} {legs.unit}{scale} + zero {legs.zero()[k]:g} mm = {lengths_mm[i, k]:.6g} mm"


def position_mm(values: np.ndarray, unit: str) -> np.ndarray:
    """(n, 3) positions in mm."""
    return MM_PER_UNIT[unit] * np.asarray(values, dtype=float)


def quaternion_matrix(q_wxyz: np.ndarray) -> np.ndarray:
    """(n, 3, 3) rotation matrices of unit Hamilton quaternions (n, 4) = [w, x, y, z]."""
    w, x, y, z = np.moveaxis(np.asarray(q_wxyz, dtype=float), -1, 0)
    return np.stack([
        np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], axis=-1),
        np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], axis=-1),
        np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], axis=-1),
    ], axis=-2)


def _from_quaternion(values: np.ndarray, scalar_first: bool) -> np.ndarray:
    q = values if scalar_first else values[:, [3, 0, 1, 2]]
    norm = np.linalg.norm(q, axis=1)
    bad = np.abs(norm - 1.0) > QUATERNION_NORM_TOLERANCE
    if np.any(bad):
        i = int(np.argmax(bad))
        raise ValueProblem(i, 0, f"quaternion norm {norm[i]:.6g}, not 1 (tolerance {QUATERNION_NORM_TOLERANCE:g}): "
                           "these columns are not a unit quaternion of this kind")
    R = quaternion_matrix(q / norm[:, None])
    return pose_from_matrix(R, np.zeros((len(q), 3)))[:, 3:]


def _from_matrix(values: np.ndarray) -> np.ndarray:
    R = values.reshape(-1, 3, 3)
    error = np.max(np.abs(np.swapaxes(R, 1, 2) @ R - np.eye(3)), axis=(1, 2))
    det = np.linalg.det(R)
    bad = (error > MATRIX_TOLERANCE) | (det <= 0)
    if np.any(bad):
        i = int(np.argmax(bad))
        why = "a reflection (determinant < 0)" if det[i] <= 0 else f"not orthonormal (|R^T R - I| = {error[i]:.3g})"
        raise ValueProblem(i, 0, f"the 9 values (row-major) are {why}: not a rotation matrix")
    U, _, Vt = np.linalg.svd(R)
    return pose_from_matrix(U @ Vt, np.zeros((len(R), 3)))[:, 3:]


def _from_rotation(R: Rotation) -> np.ndarray:
    return pose_from_matrix(R.as_matrix().reshape(-1, 3, 3), np.zeros((len(R), 3)))[:, 3:]


def orientation_deg(values: np.ndarray, kind: str, sequence: str | None = None) -> np.ndarray:
    """(n, 3) roll, pitch, yaw in degrees from (n, k) orientation columns of the given kind (Euler kinds: angles in
    the order of `sequence`, scipy's convention; rotation vectors: axis times angle)."""
    v = np.asarray(values, dtype=float)
    if kind in ("euler_deg", "euler_rad"):
        if sequence is None:
            raise ValueError("the euler kinds need a sequence")
        return _from_rotation(Rotation.from_euler(sequence, v, degrees=kind == "euler_deg"))
    if kind in ("rotvec_deg", "rotvec_rad"):
        angle = np.linalg.norm(v, axis=1)
        if kind == "rotvec_rad" and np.any(angle > np.pi + 1e-6):
            i = int(np.argmax(angle))
            raise ValueProblem(i, 0, f"rotation vector of {angle[i]:g} rad, more than π: are these degrees "
                               "(rotvec_deg)?")
        return _from_rotation(Rotation.from_rotvec(v, degrees=kind == "rotvec_deg"))
    if kind == "rpy_deg":
        return v.copy()
    if kind == "rpy_rad":
        limits = np.array([np.pi, np.pi / 2, np.pi]) + 1e-9
        bad = np.abs(v) > limits
        if np.any(bad):
            i, k = (int(x) for x in np.argwhere(bad)[0])
            raise ValueProblem(i, k, f"{v[i, k]:g} rad is beyond ±{limits[k]:.4f} rad: are these degrees (rpy_deg)?")
        return np.degrees(v)
    if kind in ("quaternion_xyzw", "quaternion_wxyz"):
        return _from_quaternion(v, scalar_first=kind == "quaternion_wxyz")
    if kind == "matrix":
        return _from_matrix(v)
    raise ValueError(f"unknown orientation kind {kind!r}")


def pose_limits(robot: Robot | None) -> np.ndarray:
    """(6, 2) plausible [low, high] per pose axis: the robot's workspace widened as the recording format does."""
    generic = np.array([[-np.inf, np.inf]] * 3 + [[-180.0, 180.0], [-90.0, 90.0], [-180.0, 180.0]])
    if robot is None:
        return generic
    margin = np.array([POSITION_MARGIN_MM] * 3 + [ANGLE_MARGIN_DEG] * 3)
    limits = robot.workspace + np.outer(margin, [-1.0, 1.0])
    return np.column_stack([np.maximum(limits[:, 0], generic[:, 0]), np.minimum(limits[:, 1], generic[:, 1])])


def check_pose(pose: np.ndarray, robot: Robot | None) -> None:
    """Raise a ValueProblem at (row, axis) for the first pose value outside ``pose_limits``."""
    limits = pose_limits(robot)
    bad = (pose < limits[:, 0]) | (pose > limits[:, 1])
    if not np.any(bad):
        return
    i, k = (int(x) for x in np.argwhere(bad)[0])
    unit = "mm" if k < 3 else "deg"
    margin = f"{POSITION_MARGIN_MM:g} mm" if k < 3 else f"{ANGLE_MARGIN_DEG:g} deg"
    where = "the plausible range" if robot is None else f"the robot's workspace widened by {margin}"
    raise ValueProblem(i, k, f"{AXES[k]} = {pose[i, k]:.6g} {unit} after conversion, outside {where} "
                       f"[{limits[k, 0]:g}, {limits[k, 1]:g}] {unit}: check the unit or kind (poses in the "
                       "instrument's own frame: set [frame] align)")
