"""Platform pose from measured points (CMM sphere centres, laser tracker targets), by rigid registration of the
known layouts.

The instrument's frame is arbitrary: registering the base points gives T_instrument<-base, registering the platform
points gives T_instrument<-platform, and the pose is T_base<-platform = inv(T_instrument<-base)
T_instrument<-platform, so the instrument's placement cancels. ``pose_from_points`` takes any two layouts (at least
three points each, not on a line: a tracker's platform nests and base monuments); ``pose_from_spheres`` is it with the
robot file's CMM sphere layouts. Poses are [x, y, z mm, roll, pitch, yaw deg] with R = Rz(yaw) Ry(pitch) Rx(roll).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from hilcal.robot import Robot


@dataclass(frozen=True)
class PoseFit:
    """Measured pose(s) and the quality of the two registrations behind each."""

    pose: np.ndarray
    """(6,) or (N, 6): [x, y, z mm, roll, pitch, yaw deg] of the platform frame in the base frame."""
    rms_residual_mm: np.ndarray
    """(2,) or (N, 2): RMS sphere-centre residual of the [platform, base] registration, mm."""

    @property
    def platform_rms_mm(self) -> np.ndarray | float:
        """RMS residual of the platform-sphere registration, mm."""
        return self.rms_residual_mm[..., 0]

    @property
    def base_rms_mm(self) -> np.ndarray | float:
        """RMS residual of the base-sphere registration, mm."""
        return self.rms_residual_mm[..., 1]


def pose_from_matrix(R: np.ndarray, t_mm: np.ndarray) -> np.ndarray:
    """[x, y, z mm, roll, pitch, yaw deg] of rotation(s) (..., 3, 3) and translation(s) (..., 3)."""
    R = np.asarray(R, dtype=float)
    t = np.asarray(t_mm, dtype=float)
    roll = np.arctan2(R[..., 2, 1], R[..., 2, 2])
    pitch = -np.arcsin(np.clip(R[..., 2, 0], -1.0, 1.0))
    yaw = np.arctan2(R[..., 1, 0], R[..., 0, 0])
    return np.concatenate([t, np.degrees(np.stack([roll, pitch, yaw], axis=-1))], axis=-1)


def rigid_fit(model: np.ndarray, measured: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Least-squares rigid transform with measured ~ R model + t (Kabsch/SVD), batched over leading axes.

    Returns (R (..., 3, 3), t (..., 3), rms residual (...) in the units of the points).
    """
    p = np.asarray(model, dtype=float)
    q = np.asarray(measured, dtype=float)
    p_mean = p.mean(axis=-2, keepdims=True)
    q_mean = q.mean(axis=-2, keepdims=True)
    H = np.swapaxes(p - p_mean, -1, -2) @ (q - q_mean)
    U, _, Vt = np.linalg.svd(H)
    V = np.swapaxes(Vt, -1, -2)
    d = np.sign(np.linalg.det(V @ np.swapaxes(U, -1, -2)))
    D = np.zeros((*d.shape, 3, 3))
    D[..., 0, 0] = 1.0
    D[..., 1, 1] = 1.0
    D[..., 2, 2] = d
    R = V @ D @ np.swapaxes(U, -1, -2)
    t = q_mean[..., 0, :] - np.einsum("...ij,...j->...i", R, p_mean[..., 0, :])
    fitted = np.einsum("...ij,...kj->...ki", R, p) + t[..., None, :]
    rms = np.sqrt(np.mean(np.sum((fitted - q) ** 2, axis=-1), axis=-1))
    return R, t, rms


def _check_measured(name: str, measured: np.ndarray, layout: np.ndarray, what: str) -> np.ndarray:
    """Measured points as a float array shaped like their layout (optionally batched)."""
    m = np.asarray(measured, dtype=float)
    k = layout.shape[0]
    if m.shape[-2:] != (k, 3) or m.ndim not in (2, 3):
        raise ValueError(f"{name} must have shape ({k}, 3) or (N, {k}, 3) like {what}; got {m.shape}")
    if not np.all(np.isfinite(m)):
        raise ValueError(f"{name} contains NaN or infinite coordinates")
    return m


def _check_layout(name: str, layout: np.ndarray) -> np.ndarray:
    """A layout of at least three points (k, 3)."""
    a = np.asarray(layout, dtype=float)
    if a.ndim != 2 or a.shape[1] != 3 or a.shape[0] < 3 or not np.all(np.isfinite(a)):
        raise ValueError(f"{name} must be at least 3 points of 3 finite coordinates, got shape {a.shape}")
    return a


def pose_from_points(platform_measured: np.ndarray, platform_layout: np.ndarray, base_measured: np.ndarray,
                     base_layout: np.ndarray, what: str = "their layout") -> PoseFit:
    """Platform pose(s) in the base frame from points measured in any instrument frame (mm, deg).

    ``platform_layout`` (M, 3) holds the platform points in the platform frame, ``base_layout`` (K, 3) the base points
    in the base frame (M, K >= 3). Accepts one measurement ((M, 3), (K, 3)) or a batch ((N, M, 3), (N, K, 3)), the
    points in their layouts' order.
    """
    p_layout = _check_layout("platform_layout", platform_layout)
    b_layout = _check_layout("base_layout", base_layout)
    plat = _check_measured("platform_measured", platform_measured, p_layout, what)
    base = _check_measured("base_measured", base_measured, b_layout, what)
    if (plat.ndim == 3) != (base.ndim == 3) or (plat.ndim == 3 and plat.shape[0] != base.shape[0]):
        raise ValueError(
            f"platform_measured {plat.shape} and base_measured {base.shape} must both be single measurements "
            "or batches of the same length"
        )
    R_cp, t_cp, rms_p = rigid_fit(p_layout, plat)
    R_cb, t_cb, rms_b = rigid_fit(b_layout, base)
    R_cb_T = np.swapaxes(R_cb, -1, -2)
    R = R_cb_T @ R_cp
    t = np.einsum("...ij,...j->...i", R_cb_T, t_cp - t_cb)
    return PoseFit(pose=pose_from_matrix(R, t), rms_residual_mm=np.stack([rms_p, rms_b], axis=-1))


def pose_from_spheres(platform_measured: np.ndarray, base_measured: np.ndarray, robot: Robot) -> PoseFit:
    """Platform pose(s) in the base frame from sphere centres measured in any CMM frame (mm, deg).

    Accepts one measurement ((M, 3), (K, 3)) or a batch ((N, M, 3), (N, K, 3)), sphere order as in the robot
    file; M, K are the robot's numbers of platform and base spheres.
    """
    return pose_from_points(platform_measured, robot.platform_spheres, base_measured, robot.base_spheres,
                            "the robot file")


PERTURBATION_MM = 1e-3
"""Central-difference step of a sphere coordinate in ``sphere_noise_covariance``."""


def sphere_noise_covariance(robot: Robot, poses: np.ndarray, sigma_mm: float, length_mm: float) -> np.ndarray:
    """[N, 6, 6] pose covariance from isotropic sphere-centre noise, propagated through the registration, in the
    residual metric of ``hilcal.error_models.pose_difference`` (mm, rotations as mm at `length_mm`).

    The CMM frame cancels in the registration and the noise is isotropic, so the base frame is used as
    the CMM frame. The Jacobian is taken by central differences of `pose_from_spheres`.
    """
    from hilcal.error_models import pose_difference
    from hilcal.kinematics import split_pose

    q = np.atleast_2d(np.asarray(poses, dtype=float))
    R, t = split_pose(q)
    platform = np.einsum("nij,kj->nki", R, robot.platform_spheres) + t[:, None, :]
    base = np.broadcast_to(robot.base_spheres, (len(q), *robot.base_spheres.shape))
    points = np.concatenate([platform, base], axis=1)
    n_p = robot.platform_spheres.shape[0]
    n_coords = points.shape[1] * 3
    jac = np.empty((len(q), 6, n_coords))
    for j in range(n_coords):
        step = np.zeros(points.shape[1:]).reshape(-1)
        step[j] = PERTURBATION_MM
        step = step.reshape(points.shape[1:])
        plus = pose_from_spheres((points + step)[:, :n_p], (points + step)[:, n_p:], robot).pose
        minus = pose_from_spheres((points - step)[:, :n_p], (points - step)[:, n_p:], robot).pose
        jac[:, :, j] = pose_difference(plus, minus, length_mm) / (2 * PERTURBATION_MM)
    return sigma_mm**2 * jac @ np.swapaxes(jac, 1, 2)


def _expected_max_rms_squared(robot: Robot) -> float:
    """E[sphere_fit_rms_mm^2] / sigma^2 for the column's definition: the larger of the two registrations' RMS.

    A rigid registration of M spheres leaves 3M - 6 degrees of freedom, so RMS^2 = sigma^2 chi2(3M-6) / M.
    """
    dists = []
    for m in (robot.platform_spheres.shape[0], robot.base_spheres.shape[0]):
        dof = 3 * m - 6
        dists.append((dof, m))

    from scipy import integrate  # 0.13 s of start-up, for this one integral
    from scipy.special import chdtr

    def cdf(x: float) -> float:
        return float(np.prod([chdtr(dof, x * m) if dof > 0 else 1.0 for dof, m in dists]))

    value, _ = integrate.quad(lambda x: 1.0 - cdf(x), 0.0, np.inf, limit=200)
    return float(value)


def sigma_from_sphere_fit(rms_mm: np.ndarray, robot: Robot) -> tuple[float, float]:
    """Sphere-centre sigma (mm) and its degrees of freedom from the per-row registration RMS column."""
    values = np.asarray(rms_mm, dtype=float)
    values = values[np.isfinite(values)]
    factor = _expected_max_rms_squared(robot)
    dof = values.size * 3 * (min(robot.platform_spheres.shape[0], robot.base_spheres.shape[0]) - 2)
    return float(np.sqrt(np.mean(values**2) / factor)), float(dof)
