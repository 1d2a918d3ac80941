"""Inverse and forward kinematics and statics of a 6-6 Gough platform, vectorized over poses.

Poses are arrays [..., 6] = [x, y, z (mm), roll, pitch, yaw (deg)], R = Rz(yaw) Ry(pitch) Rx(roll).
Leg lengths are the lengths the controller *reports*; the geometric joint-to-joint length is
reported + dl0 (the stroke-zero offset error of each leg).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from hilcal.robot import Robot, rotation_matrix

N_LEGS = 6


class KinematicsError(ValueError):
    """Base class for poses the kinematics cannot solve; ``indices`` names the offending rows."""

    def __init__(self, message: str, indices: np.ndarray):
        super().__init__(message)
        self.indices = np.asarray(indices)


class ForwardKinematicsError(KinematicsError):
    """Newton–Raphson did not converge (leg lengths unreachable or a bad initial guess)."""


class SingularPoseError(KinematicsError):
    """The pose is at or near a singularity: leg lengths do not determine the pose reliably."""


@dataclass(frozen=True)
class Geometry:
    """Joint positions a (platform frame), b (base frame), and leg offset errors dl0, all mm."""

    a: np.ndarray
    b: np.ndarray
    dl0: np.ndarray = field(default_factory=lambda: np.zeros(N_LEGS))

    @classmethod
    def nominal(cls, robot: Robot) -> Geometry:
        return cls(robot.a, robot.b, np.zeros(N_LEGS))

    def perturbed(self, dp: np.ndarray) -> Geometry:
        """Apply the 42 geometric errors, per leg [da_x, da_y, da_z, db_x, db_y, db_z, dl0] (mm)."""
        d = np.asarray(dp, dtype=float).reshape(N_LEGS, 7)
        return Geometry(self.a + d[:, 0:3], self.b + d[:, 3:6], self.dl0 + d[:, 6])


def split_pose(poses: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Poses [..., 6] (mm, deg) -> rotation matrices [..., 3, 3] and translations [..., 3] (mm)."""
    q = np.asarray(poses, dtype=float)
    return rotation_matrix(np.radians(q[..., 3:6])), q[..., 0:3]


def leg_vectors(geom: Geometry, R: np.ndarray, t: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Leg vectors R a_i + t - b_i [..., 6, 3], their lengths [..., 6] and unit directions [..., 6, 3]."""
    _, v, length = leg_geometry(geom, R, t)
    return v, length, v / length[..., None]


def leg_geometry(geom: Geometry, R: np.ndarray, t: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """R a_i [..., 6, 3], the leg vectors [..., 6, 3] and their lengths [..., 6]: what `leg_vectors` and the
    Jacobians share (computed once where both are needed)."""
    ra = np.swapaxes(R @ geom.a.T, -1, -2)
    v = ra + t[..., None, :] - geom.b
    return ra, v, np.linalg.norm(v, axis=-1)


def inverse_kinematics(geom: Geometry, poses: np.ndarray) -> np.ndarray:
    """Reported leg lengths [..., 6] (mm) that put the platform at the given poses (eq. 4)."""
    R, t = split_pose(poses)
    _, length, _ = leg_vectors(geom, R, t)
    return length - geom.dl0


def inverse_jacobian(geom: Geometry, R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """J [..., 6, 6] with dl = J [dt (mm); dw (rad)], dw the small rotation in the base frame.

    Row i is [u_i, (R a_i) x u_i]: the classic Stewart-platform inverse Jacobian.
    """
    ra, v, length = leg_geometry(geom, R, t)
    u = v / length[..., None]
    return np.concatenate([u, np.cross(ra, u)], axis=-1)


def rpy_rate_matrix(rpy_rad: np.ndarray) -> np.ndarray:
    """E [..., 3, 3] with dw = E d[roll, pitch, yaw] for R = Rz Ry Rx (the paper's eq. 9)."""
    rpy = np.asarray(rpy_rad, dtype=float)
    cp, sp = np.cos(rpy[..., 1]), np.sin(rpy[..., 1])
    cy, sy = np.cos(rpy[..., 2]), np.sin(rpy[..., 2])
    E = np.zeros((*rpy.shape[:-1], 3, 3))
    E[..., 0, 0] = cy * cp
    E[..., 0, 1] = -sy
    E[..., 1, 0] = sy * cp
    E[..., 1, 1] = cy
    E[..., 2, 0] = -sp
    E[..., 2, 2] = 1.0
    return E


def pose_jacobian(geom: Geometry, poses: np.ndarray) -> np.ndarray:
    """d(reported lengths)/d(pose) [..., 6, 6] with the pose in (mm, rad): the analytic Newton Jacobian."""
    q = np.asarray(poses, dtype=float)
    R, t = split_pose(q)
    J = inverse_jacobian(geom, R, t)
    Jq = J.copy()
    Jq[..., 3:] = J[..., 3:] @ rpy_rate_matrix(np.radians(q[..., 3:6]))
    return Jq


def scaled_condition(J: np.ndarray, length_mm: float) -> np.ndarray:
    """Condition number of the inverse Jacobian with rotations expressed as mm at radius length_mm."""
    Js = J.copy()
    Js[..., 3:] /= length_mm
    s = np.linalg.svd(Js, compute_uv=False)
    with np.errstate(divide="ignore"):
        return s[..., 0] / s[..., -1]


def _singular_rows(J: np.ndarray, length_mm: float, max_condition: float) -> tuple[np.ndarray, np.ndarray]:
    """Rows of J [N, 6, 6] whose `scaled_condition` is not below max_condition, and their condition numbers.

    The singular values are computed only where a cheap bound does not already clear the pose: the condition number
    is at most |Js|_F |Js^-1|_F (Frobenius norms), and a pose whose bound is below half the limit is well inside it."""
    Js = J.copy()
    Js[..., 3:] /= length_mm
    try:
        with np.errstate(all="ignore"):
            bound = np.sqrt(np.sum(Js**2, axis=(1, 2)) * np.sum(np.linalg.inv(Js) ** 2, axis=(1, 2)))
    except np.linalg.LinAlgError:
        bound = np.full(len(J), np.inf)
    check = np.flatnonzero(~(bound < 0.5 * max_condition))
    if not check.size:
        return check, np.zeros(0)
    cond = scaled_condition(J[check], length_mm)
    bad = ~(cond < max_condition)
    return check[bad], cond[bad]


def _characteristic_length(geom: Geometry) -> float:
    a = geom.a - geom.a.mean(axis=0)
    return float(np.sqrt(np.mean(np.sum(a**2, axis=1))))


def forward_kinematics(
    geom: Geometry,
    lengths: np.ndarray,
    guess: np.ndarray,
    *,
    tol_mm: float = 1e-10,
    max_iter: int = 50,
    max_condition: float = 1e6,
) -> np.ndarray:
    """Poses [N, 6] (mm, deg) whose reported leg lengths equal `lengths` [N, 6], by batched Newton–Raphson.

    `guess` is [6] or [N, 6] (e.g. the home or the commanded pose). Raises ForwardKinematicsError
    for rows that do not converge and SingularPoseError for rows near a singularity.
    """
    L = np.atleast_2d(np.asarray(lengths, dtype=float))
    n = L.shape[0]
    q = np.array(np.broadcast_to(np.asarray(guess, dtype=float), (n, 6)))
    q[:, 3:] = np.radians(q[:, 3:])
    target = L + geom.dl0
    active = np.ones(n, dtype=bool)
    for _ in range(max_iter):
        idx = np.flatnonzero(active)
        if idx.size == 0:
            break
        qa = q[idx]
        R = rotation_matrix(qa[:, 3:])
        ra, v, length = leg_geometry(geom, R, qa[:, :3])
        f = length - target[idx]
        done = np.max(np.abs(f), axis=1) < tol_mm
        active[idx[done]] = False
        if done.all():
            break
        idx, qa, f, ra, v, length = idx[~done], qa[~done], f[~done], ra[~done], v[~done], length[~done]
        u = v / length[..., None]
        J = np.concatenate([u, np.cross(ra, u)], axis=-1)  # inverse_jacobian from the legs just measured
        J[:, :, 3:] = J[:, :, 3:] @ rpy_rate_matrix(qa[:, 3:])
        try:
            step = np.linalg.solve(J, -f[..., None])[..., 0]
        except np.linalg.LinAlgError:
            step = np.einsum("nij,nj->ni", np.linalg.pinv(J), -f)
        q[idx] = qa + step
    if active.any():
        bad = np.flatnonzero(active)
        raise ForwardKinematicsError(
            f"forward kinematics did not converge for {bad.size} of {n} pose(s) (rows {bad[:10].tolist()}): "
            "leg lengths unreachable or initial guess too far",
            bad,
        )
    R = rotation_matrix(q[:, 3:])
    singular, cond = _singular_rows(inverse_jacobian(geom, R, q[:, :3]), _characteristic_length(geom), max_condition)
    if singular.size:
        raise SingularPoseError(
            f"{singular.size} pose(s) near a singularity (rows {singular[:10].tolist()}, "
            f"condition {cond[0]:.3g} > {max_condition:.3g}): the pose is not determined by the legs",
            singular,
        )
    q[:, 3:] = np.degrees(q[:, 3:])
    return q


def gravity_wrench(robot: Robot, poses: np.ndarray) -> np.ndarray:
    """Gravity wrench [..., 6] on the moving mass: force (N) and moment (N·mm) about the platform origin."""
    R, _ = split_pose(poses)
    force = np.array([0.0, 0.0, -robot.moving_mass_kg * robot.gravity_mps2])
    com = np.einsum("...jk,k->...j", R, robot.com)
    moment = np.cross(com, force)
    return np.concatenate([np.broadcast_to(force, moment.shape), moment], axis=-1)


def leg_forces(geom: Geometry, poses: np.ndarray, wrench: np.ndarray) -> np.ndarray:
    """Axial leg forces [..., 6] (N, positive = compression) that balance an external wrench on the platform.

    Static equilibrium: sum f_i u_i + F = 0 and sum (R a_i) x f_i u_i + M = 0, i.e. J^T f = -w.
    """
    R, t = split_pose(poses)
    J = inverse_jacobian(geom, R, t)
    w = np.broadcast_to(np.asarray(wrench, dtype=float), J.shape[:-1])
    return np.linalg.solve(np.swapaxes(J, -1, -2), -w[..., None])[..., 0]
