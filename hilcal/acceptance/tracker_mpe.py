"""A laser tracker's maximum permissible error carried into the uncertainty of a measured pose.

A tracker's accuracy is stated as a maximum permissible error that grows with the distance, U(d) = ±(a + b d) (for
example 15 µm + 6 µm/m). The certificate reads it as the expanded uncertainty U (k = 2) of every coordinate of a
measured point at its distance d from the tracker: u = U(d) / 2 per coordinate. The pose is registered from the
platform targets and the base monuments (``hilcal.pose_measurement.pose_from_points``), so its covariance follows by
seeded Monte Carlo as for the CMM (``hilcal.acceptance.uncertainty.cmm_pose_covariance``), each target with its own
u. The tracker's frame cancels in the registration; only its distance to each target matters.
"""

from __future__ import annotations

import numpy as np

from hilcal.kinematics import split_pose
from hilcal.pose_measurement import pose_from_points

K_MPE = 2.0
"""The MPE is read as an expanded uncertainty with this coverage factor."""


def mpe_mm(distance_mm: np.ndarray | float, constant_um: float, per_m_um: float) -> np.ndarray:
    """U(d) = constant + per_m · d, in mm, for distances d in mm."""
    return (constant_um + per_m_um * np.asarray(distance_mm, dtype=float) / 1000.0) / 1000.0


def tracker_origin_mm(alignment: np.ndarray) -> np.ndarray:
    """Where the tracker stands in the base frame (3,), from T_tracker<-base (4x4)."""
    T = np.asarray(alignment, dtype=float)
    return -T[:3, :3].T @ T[:3, 3]


def target_points_mm(platform_layout: np.ndarray, base_layout: np.ndarray, pose: np.ndarray) -> np.ndarray:
    """(M + K, 3) the platform targets at `pose` and the base monuments, in the base frame."""
    R, t = split_pose(np.asarray(pose, dtype=float))
    return np.vstack([np.asarray(platform_layout, dtype=float) @ R.T + t, np.asarray(base_layout, dtype=float)])


def target_uncertainty_mm(platform_layout: np.ndarray, base_layout: np.ndarray, pose: np.ndarray,
                          origin_mm: np.ndarray, constant_um: float, per_m_um: float) -> np.ndarray:
    """(M + K,) U (k = 2) per coordinate of each target, platform first, at its distance from the tracker."""
    points = target_points_mm(platform_layout, base_layout, pose)
    return mpe_mm(np.linalg.norm(points - np.asarray(origin_mm, dtype=float), axis=1), constant_um, per_m_um)


def tracker_pose_covariance(platform_layout: np.ndarray, base_layout: np.ndarray, pose: np.ndarray,
                            origin_mm: np.ndarray, constant_um: float, per_m_um: float, *, draws: int = 4000,
                            seed: int = 0) -> np.ndarray:
    """(6, 6) covariance (mm, deg) of one pose measured with the tracker at `origin_mm` (base frame): every coordinate
    of every target drawn with u = U(d) / 2 at its distance, the pose registered from them."""
    platform_layout = np.asarray(platform_layout, dtype=float)
    base_layout = np.asarray(base_layout, dtype=float)
    q = np.asarray(pose, dtype=float)
    points = target_points_mm(platform_layout, base_layout, q)
    u = target_uncertainty_mm(platform_layout, base_layout, q, origin_mm, constant_um, per_m_um) / K_MPE
    if not np.all(u > 0):
        raise ValueError("the tracker's MPE must be positive at every target")
    rng = np.random.default_rng(seed)
    drawn = points + rng.normal(0.0, 1.0, (draws, *points.shape)) * u[:, None]
    m = len(platform_layout)
    fits = pose_from_points(drawn[:, :m], platform_layout, drawn[:, m:], base_layout).pose
    d = fits - q
    d[:, 3:] = (d[:, 3:] + 180.0) % 360.0 - 180.0
    return np.cov(d, rowvar=False)


def pose_sigma(covariance: np.ndarray) -> tuple[float, float]:
    """One standard deviation per position coordinate (mm) and per orientation axis (deg): the root mean square of
    the covariance's diagonal in each block (the noise yardstick a diagnosis takes as ``pose_sigma``)."""
    diag = np.diag(np.asarray(covariance, dtype=float))
    return float(np.sqrt(np.mean(diag[:3]))), float(np.sqrt(np.mean(diag[3:])))
