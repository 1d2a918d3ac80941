"""Poses logged in an instrument's own frame, brought into the robot's base frame.

A laser tracker or a 6-DoF probe reports the pose of its target T_i in its own frame, not the platform frame in
the base frame. With the nominal geometry, the leg lengths give the platform's pose B_i, and

    T_i = X · B_i · Y

where X is the base frame in the instrument's frame and Y the target in the platform frame, both rigid and the
same for every row. X and Y are found in closed form (rotations from the rotation axes between rows, Kabsch;
translations by linear least squares) and refined by nonlinear least squares; the aligned pose of each row is
X^-1 · T_i · Y^-1. What the nominal geometry cannot explain stays in the poses: the geometric errors that look
like a frame change are absorbed by X and Y (the 42-parameter model absorbs them the same way), the rest is for
the identification and the diagnosis.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation

from hilcal.kinematics import Geometry, KinematicsError, forward_kinematics, split_pose
from hilcal.pose_measurement import pose_from_matrix
from hilcal.robot import Robot

MIN_ROWS = 6
"""Fewer rows than this cannot pin down two rigid frames (12 unknowns) against noise."""
MIN_ROTATION_SPREAD_DEG = 0.5
"""Below this spread of the platform's orientation, the target's offset cannot be told from the base frame's."""


class FrameAlignmentError(ValueError):
    """The rows cannot give the instrument's frame (too few, no rotation, legs that no pose fits)."""


@dataclass(frozen=True)
class FrameAlignment:
    """The instrument's frame (X) and the target's place on the platform (Y), each [x, y, z mm, roll, pitch, yaw deg],
    and how well the nominal geometry explains the rows after alignment (RMS position mm, orientation deg)."""

    base_in_instrument: np.ndarray
    target_in_platform: np.ndarray
    rms_position_mm: float
    rms_orientation_deg: float
    n_rows: int

    def apply(self, poses: np.ndarray) -> np.ndarray:
        """(n, 6) logged poses T_i as platform poses in the base frame: X^-1 · T_i · Y^-1."""
        RX, tX = _matrix(self.base_in_instrument)
        RY, tY = _matrix(self.target_in_platform)
        RT, tT = split_pose(np.atleast_2d(poses))
        R = RX.T @ RT @ RY.T
        t = np.einsum("ij,nj->ni", RX.T, tT - tX) - R @ tY
        return pose_from_matrix(R, t)

    def describe(self) -> str:
        x, y = self.base_in_instrument, self.target_in_platform
        return (f"base frame in the instrument's frame at ({x[0]:.3f}, {x[1]:.3f}, {x[2]:.3f}) mm, roll/pitch/yaw "
                f"({x[3]:.4f}, {x[4]:.4f}, {x[5]:.4f}) deg; target on the platform at ({y[0]:.3f}, {y[1]:.3f}, "
                f"{y[2]:.3f}) mm, ({y[3]:.4f}, {y[4]:.4f}, {y[5]:.4f}) deg; {self.n_rows} rows, nominal geometry "
                f"explains them to {self.rms_position_mm:.4f} mm / {self.rms_orientation_deg:.5f} deg RMS (geometric "
                "errors and noise)")


def _matrix(pose: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    R, t = split_pose(np.atleast_2d(pose))
    return R[0], t[0]


def _kabsch(u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Rotation R minimising sum |v_k - R u_k|^2 (rows are vectors)."""
    U, _, Vt = np.linalg.svd(v.T @ u)
    d = np.sign(np.linalg.det(U @ Vt))
    return U @ np.diag([1.0, 1.0, d]) @ Vt


def _initial(RT: np.ndarray, tT: np.ndarray, RB: np.ndarray, tB: np.ndarray) -> np.ndarray:
    """Closed-form X and Y as a 12-vector [rotvec X, t X, rotvec Y, t Y]."""
    u = Rotation.from_matrix(RB[1:] @ np.swapaxes(RB[:1], 1, 2)).as_rotvec()
    v = Rotation.from_matrix(RT[1:] @ np.swapaxes(RT[:1], 1, 2)).as_rotvec()
    RX = _kabsch(u, v)
    RY = Rotation.from_matrix(np.swapaxes(RB, 1, 2) @ RX.T @ RT).mean().as_matrix()
    n = len(RT)
    A = np.concatenate([RX @ RB, np.broadcast_to(np.eye(3), (n, 3, 3))], axis=2).reshape(3 * n, 6)
    b = (tT - tB @ RX.T).reshape(-1)
    ty_tx = np.linalg.lstsq(A, b, rcond=None)[0]
    return np.concatenate([Rotation.from_matrix(RX).as_rotvec(), ty_tx[3:], Rotation.from_matrix(RY).as_rotvec(),
                           ty_tx[:3]])


def _residuals(x: np.ndarray, RT: np.ndarray, tT: np.ndarray, RB: np.ndarray, tB: np.ndarray,
               length_mm: float) -> np.ndarray:
    """Position (mm) and orientation (rad x characteristic length) misfit of T_i against X · B_i · Y."""
    RX, tX = Rotation.from_rotvec(x[:3]).as_matrix(), x[3:6]
    RY, tY = Rotation.from_rotvec(x[6:9]).as_matrix(), x[9:]
    R = RX @ RB @ RY
    t = (RX @ (RB @ tY + tB)[..., None])[..., 0] + tX
    rot = Rotation.from_matrix(np.swapaxes(R, 1, 2) @ RT).as_rotvec()
    return np.concatenate([t - tT, rot * length_mm], axis=1).ravel()


def align_frames(logged: np.ndarray, legs_mm: np.ndarray, robot: Robot) -> FrameAlignment:
    """X and Y for rows of logged target poses (n, 6: mm, deg, in the instrument's frame) and leg lengths (n, 6)."""
    logged = np.atleast_2d(np.asarray(logged, dtype=float))
    n = len(logged)
    if n < MIN_ROWS:
        raise FrameAlignmentError(f"{n} rows cannot give the instrument's frame: at least {MIN_ROWS} are needed")
    try:
        nominal = forward_kinematics(Geometry.nominal(robot), legs_mm, robot.home)
    except KinematicsError as e:
        raise FrameAlignmentError(f"the nominal geometry finds no pose for some rows' leg lengths ({e}): check "
                                  "[legs] and the robot file") from None
    RT, tT = split_pose(logged)
    RB, tB = split_pose(nominal)
    spread = np.degrees(np.max(np.linalg.norm(
        Rotation.from_matrix(RB @ np.swapaxes(RB[:1], 1, 2)).as_rotvec(), axis=1)))
    if spread < MIN_ROTATION_SPREAD_DEG:
        raise FrameAlignmentError(f"the platform turns by at most {spread:.3g} deg across the rows: without "
                                  f"{MIN_ROTATION_SPREAD_DEG:g} deg or more the target's place on the platform cannot "
                                  "be told from the instrument's frame")
    length = robot.characteristic_length_mm
    fit = least_squares(_residuals, _initial(RT, tT, RB, tB), args=(RT, tT, RB, tB, length), method="lm",
                        x_scale="jac")
    r = fit.fun.reshape(n, 6)
    X = pose_from_matrix(Rotation.from_rotvec(fit.x[:3]).as_matrix()[None], fit.x[3:6][None])[0]
    Y = pose_from_matrix(Rotation.from_rotvec(fit.x[6:9]).as_matrix()[None], fit.x[9:][None])[0]
    return FrameAlignment(X, Y, float(np.sqrt(np.mean(np.sum(r[:, :3] ** 2, axis=1)))),
                          float(np.degrees(np.sqrt(np.mean(np.sum((r[:, 3:] / length) ** 2, axis=1))))), n)


def align_frames_shared_target(parts: list[tuple[np.ndarray, np.ndarray]], robot: Robot
                               ) -> tuple[list[FrameAlignment], list[FrameAlignment]]:
    """One instrument frame X_f per part (logged poses, leg lengths) and one target place Y for all: the instrument
    set up anew for every file, the target left on the platform. Started from each part's own alignment (its Y
    averaged), refined jointly. Returns the joint alignments (each with its part's RMS) and the parts' own."""
    own = [align_frames(logged, legs, robot) for logged, legs in parts]
    geometry, length = Geometry.nominal(robot), robot.characteristic_length_mm
    data = []
    for logged, legs in parts:
        RT, tT = split_pose(np.atleast_2d(np.asarray(logged, dtype=float)))
        RB, tB = split_pose(forward_kinematics(geometry, legs, robot.home))
        data.append((RT, tT, RB, tB))

    def vector(pose: np.ndarray) -> np.ndarray:
        R, t = split_pose(pose[None])
        return np.concatenate([Rotation.from_matrix(R[0]).as_rotvec(), t[0]])

    y0 = vector(pose_from_matrix(Rotation.from_matrix(np.stack([split_pose(a.target_in_platform[None])[0][0]
                                                                 for a in own])).mean().as_matrix()[None],
                                 np.mean([a.target_in_platform[:3] for a in own], axis=0)[None])[0])
    x0 = np.concatenate([y0, *[vector(a.base_in_instrument) for a in own]])

    def residuals(x: np.ndarray) -> np.ndarray:
        return np.concatenate([_residuals(np.concatenate([x[6 + 6 * k:12 + 6 * k], x[:6]]), *d, length)
                               for k, d in enumerate(data)])

    fit = least_squares(residuals, x0, method="lm", x_scale="jac")
    Y = pose_from_matrix(Rotation.from_rotvec(fit.x[:3]).as_matrix()[None], fit.x[3:6][None])[0]
    out, start = [], 0
    for k, (RT, _, _, _) in enumerate(data):
        n = len(RT)
        r = fit.fun[6 * start:6 * (start + n)].reshape(n, 6)
        start += n
        xk = fit.x[6 + 6 * k:12 + 6 * k]
        X = pose_from_matrix(Rotation.from_rotvec(xk[:3]).as_matrix()[None], xk[3:][None])[0]
        out.append(FrameAlignment(X, Y, float(np.sqrt(np.mean(np.sum(r[:, :3] ** 2, axis=1)))),
                                  float(np.degrees(np.sqrt(np.mean(np.sum((r[:, 3:] / length) ** 2, axis=1))))), n))
    return out, own
