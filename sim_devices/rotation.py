"""Rotation helpers of the simulators, in numpy on 3x3 matrices (so that the simulator starts without scipy).

Orientations are [roll, pitch, yaw] in degrees, R = Rz(yaw) Ry(pitch) Rx(roll) (intrinsic ZYX: yaw first), as in a
pose [x, y, z mm, roll, pitch, yaw deg]; rotation vectors are axis times angle, in radians. Rotations compose as
matrix products (``A @ B`` turns by B first), a rotation R maps points (N, 3) as ``points @ R.T``.
"""

from __future__ import annotations

import numpy as np

SMALL_ANGLE_RAD = 1e-12
"""Below this angle the rotation vector's matrix is I + [w]x (the next term is of the order of the angle squared)."""


def matrix_from_rpy_deg(rpy_deg: np.ndarray) -> np.ndarray:
    """Rotation matrices [..., 3, 3] of orientations [..., roll, pitch, yaw] (deg): R = Rz(yaw) Ry(pitch) Rx(roll)."""
    angles = np.radians(np.asarray(rpy_deg, dtype=float))
    cr, cp, cy = np.cos(angles[..., 0]), np.cos(angles[..., 1]), np.cos(angles[..., 2])
    sr, sp, sy = np.sin(angles[..., 0]), np.sin(angles[..., 1]), np.sin(angles[..., 2])
    R = np.empty((*angles.shape[:-1], 3, 3))
    R[..., 0, 0], R[..., 0, 1], R[..., 0, 2] = cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr
    R[..., 1, 0], R[..., 1, 1], R[..., 1, 2] = sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr
    R[..., 2, 0], R[..., 2, 1], R[..., 2, 2] = -sp, cp * sr, cp * cr
    return R


def rpy_deg_from_matrix(R: np.ndarray) -> np.ndarray:
    """[..., roll, pitch, yaw] (deg) of rotation matrices [..., 3, 3], the inverse of ``matrix_from_rpy_deg``
    (pitch in [-90, 90], roll and yaw in [-180, 180])."""
    R = np.asarray(R, dtype=float)
    roll = np.arctan2(R[..., 2, 1], R[..., 2, 2])
    pitch = np.arctan2(-R[..., 2, 0], np.hypot(R[..., 2, 1], R[..., 2, 2]))
    yaw = np.arctan2(R[..., 1, 0], R[..., 0, 0])
    return np.degrees(np.stack([roll, pitch, yaw], axis=-1))


def matrix_from_rotvec(w_rad: np.ndarray) -> np.ndarray:
    """Rotation matrix (3, 3) of the rotation vector w (3,) (rad), by Rodrigues' formula."""
    w = np.asarray(w_rad, dtype=float)
    angle = float(np.linalg.norm(w))
    K = np.array([[0.0, -w[2], w[1]], [w[2], 0.0, -w[0]], [-w[1], w[0], 0.0]])
    if angle < SMALL_ANGLE_RAD:
        return np.eye(3) + K
    return np.eye(3) + np.sin(angle) / angle * K + (1.0 - np.cos(angle)) / angle**2 * (K @ K)


def rotvec_from_matrix(R: np.ndarray) -> np.ndarray:
    """Rotation vector (3,) (rad, angle in [0, pi]) of a rotation matrix (3, 3), the inverse of
    ``matrix_from_rotvec``; accurate at every angle (near pi the axis comes from the symmetric part)."""
    R = np.asarray(R, dtype=float)
    sin_axis = 0.5 * np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])
    sin = float(np.linalg.norm(sin_axis))
    cos = 0.5 * (float(np.trace(R)) - 1.0)
    angle = float(np.arctan2(sin, cos))
    if cos > 0.0:
        return sin_axis * (angle / sin if sin > 0.0 else 1.0)
    symmetric = 0.5 * (R + R.T) - cos * np.eye(3)  # (1 - cos) axis axis^T
    row = symmetric[int(np.argmax(np.diag(symmetric)))]
    axis = row / np.linalg.norm(row)
    return angle * (axis if axis @ sin_axis >= 0.0 else -axis)


def orthonormalized(R: np.ndarray) -> np.ndarray:
    """The rotation nearest R (3, 3), for R a rotation up to rounding (one Newton step of the polar decomposition)."""
    return 1.5 * R - 0.5 * R @ (R.T @ R)


def slerp(R0: np.ndarray, R1: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Rotations (N, 3, 3) at the fractions t (N,) of the shortest turn from R0 (t = 0) to R1 (t = 1)."""
    turn = rotvec_from_matrix(R0.T @ R1)
    return np.stack([R0 @ matrix_from_rotvec(fraction * turn) for fraction in np.asarray(t, dtype=float)])
