"""Sphere fitting for CMM probing: least-squares centre (known or free radius), outlier rule, probe pattern.

Pure math, no I/O. Residuals are signed radial distances |p - c| - r (mm): positive outside the sphere.
With isotropic probing noise sigma per coordinate, each radial residual has standard deviation sigma, so
the centre covariance of a fit is sigma^2 * ``centre_cov_unit``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.optimize import least_squares

MIN_POINTS_FIXED_RADIUS = 4
"""3 unknowns; a 4th point makes the fit checkable."""
MIN_POINTS_FREE_RADIUS = 5
"""4 unknowns; a 5th point makes the fit checkable."""


class SphereFitError(ValueError):
    """The points do not determine a sphere (too few, not finite, or degenerate)."""


@dataclass(frozen=True)
class SphereFit:
    """A fitted sphere and how well the points agree with it."""

    centre_mm: np.ndarray
    """(3,) fitted centre."""
    radius_mm: float
    """The given radius (fixed fit) or the fitted one (free fit)."""
    residuals_mm: np.ndarray
    """(N,) signed radial residual of each point, |p - c| - r."""
    rms_mm: float
    """RMS of the residuals."""
    radius_fixed: bool
    """True when the radius was given, False when it was fitted."""
    centre_cov_unit: np.ndarray
    """(3, 3) centre covariance per unit variance of the radial residuals, (J^T J)^-1 restricted to the centre."""
    radius_sd_unit: float = float("nan")
    """Standard deviation of a fitted radius per unit residual standard deviation (NaN for a fixed radius);
    large when the points barely determine the radius (e.g. all on one circle)."""

    @property
    def dof(self) -> int:
        """Redundancy: points minus unknowns."""
        return len(self.residuals_mm) - (3 if self.radius_fixed else 4)

    @property
    def sigma_hat_mm(self) -> float:
        """A-posteriori residual standard deviation (NaN without redundancy)."""
        if self.dof <= 0:
            return float("nan")
        return float(np.sqrt(np.sum(self.residuals_mm**2) / self.dof))


@dataclass(frozen=True)
class RobustSphereFit:
    """A fixed-radius fit after rejecting outliers, with every point's residual kept."""

    fit: SphereFit
    """Fit over the inliers only."""
    inliers: np.ndarray
    """(N,) bool mask over the input points."""
    residuals_mm: np.ndarray
    """(N,) residual of every input point (inliers and outliers) against ``fit``."""
    threshold_mm: float
    """|residual| above this marks a point as an outlier."""

    @property
    def outliers(self) -> np.ndarray:
        """Indices of the rejected points."""
        return np.flatnonzero(~self.inliers)

    @property
    def consistent(self) -> bool:
        """True when every inlier is within the threshold (false only if too few points were left to reject)."""
        return bool(np.all(np.abs(self.residuals_mm[self.inliers]) <= self.threshold_mm))


def _check_points(points_mm: np.ndarray, minimum: int) -> np.ndarray:
    p = np.asarray(points_mm, dtype=float)
    if p.ndim != 2 or p.shape[1] != 3:
        raise SphereFitError(f"points must have shape (N, 3), got {p.shape}")
    if len(p) < minimum:
        raise SphereFitError(f"need at least {minimum} points, got {len(p)}")
    if not np.all(np.isfinite(p)):
        raise SphereFitError("points contain NaN or infinite coordinates")
    return p


def algebraic_sphere(points_mm: np.ndarray) -> tuple[np.ndarray, float]:
    """Linear (Kasa) sphere fit |p|^2 = 2 p.c + k: a starting guess; needs 4 non-coplanar points."""
    p = _check_points(points_mm, 4)
    scale = max(float(np.max(np.abs(p - p.mean(axis=0)))), 1e-12)
    origin = p.mean(axis=0)
    q = (p - origin) / scale
    A = np.column_stack([2.0 * q, np.ones(len(q))])
    b = np.sum(q**2, axis=1)
    sol, _, rank, _ = np.linalg.lstsq(A, b, rcond=None)
    if rank < 4:
        raise SphereFitError("points are coplanar (or coincident): the sphere centre is not determined")
    c = sol[:3]
    r2 = sol[3] + c @ c
    if r2 <= 0:
        raise SphereFitError("points do not lie on a sphere (negative squared radius)")
    return origin + scale * c, float(np.sqrt(r2) * scale)


def fit_sphere(
    points_mm: np.ndarray, radius_mm: float | None = None, initial_centre_mm: np.ndarray | None = None
) -> SphereFit:
    """Geometric least-squares sphere through the points; with ``radius_mm`` given only the centre is fitted.

    The start is ``initial_centre_mm`` or the algebraic fit; with a fixed radius a start on the wrong side
    of a cap of points would converge to the mirror solution, so give a start when points are nearly coplanar.
    """
    fixed = radius_mm is not None
    p = _check_points(points_mm, MIN_POINTS_FIXED_RADIUS if fixed else MIN_POINTS_FREE_RADIUS)
    if fixed and not (np.isfinite(radius_mm) and radius_mm > 0):
        raise SphereFitError(f"radius must be positive and finite, got {radius_mm}")
    if initial_centre_mm is not None:
        c0 = np.asarray(initial_centre_mm, dtype=float)
        if c0.shape != (3,) or not np.all(np.isfinite(c0)):
            raise SphereFitError(f"initial centre must be 3 finite numbers, got {initial_centre_mm!r}")
        r0 = float(radius_mm) if fixed else float(np.mean(np.linalg.norm(p - c0, axis=1)))
    else:
        c0, r0 = algebraic_sphere(p)
        if fixed:
            r0 = float(radius_mm)

    def residual(x: np.ndarray) -> np.ndarray:
        r = r0 if fixed else x[3]
        return np.linalg.norm(p - x[:3], axis=1) - r

    def jacobian(x: np.ndarray) -> np.ndarray:
        d = p - x[:3]
        u = d / np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-300)
        return -u if fixed else np.column_stack([-u, -np.ones(len(p))])

    x0 = c0 if fixed else np.append(c0, r0)
    sol = least_squares(residual, x0, jac=jacobian, method="lm", xtol=1e-15, ftol=1e-15, gtol=1e-15)
    J = jacobian(sol.x)
    JtJ = J.T @ J
    if np.linalg.cond(JtJ) > 1e12:
        raise SphereFitError("the points do not determine the sphere (ill-conditioned fit)")
    cov_full = np.linalg.inv(JtJ)
    res = residual(sol.x)
    return SphereFit(
        centre_mm=sol.x[:3].copy(),
        radius_mm=float(r0 if fixed else sol.x[3]),
        residuals_mm=res,
        rms_mm=float(np.sqrt(np.mean(res**2))),
        radius_fixed=fixed,
        centre_cov_unit=cov_full[:3, :3],
        radius_sd_unit=float("nan") if fixed else float(np.sqrt(max(cov_full[3, 3], 0.0))),
    )


def outlier_threshold_mm(probe_sigma_mm: float, k_sigma: float = 5.0, floor_mm: float = 0.005) -> float:
    """|residual| above which a probed point is an outlier: k times the probing noise, at least ``floor_mm``."""
    if probe_sigma_mm < 0 or k_sigma <= 0 or floor_mm < 0:
        raise ValueError("probe_sigma_mm and floor_mm must be >= 0 and k_sigma > 0")
    return max(k_sigma * probe_sigma_mm, floor_mm)


def fit_sphere_robust(
    points_mm: np.ndarray,
    radius_mm: float,
    threshold_mm: float,
    initial_centre_mm: np.ndarray | None = None,
) -> RobustSphereFit:
    """Fixed-radius fit rejecting outliers one at a time (backward elimination with a leave-one-out check).

    While the worst point exceeds the threshold and more than the minimum remain, the worst point is left
    out and refitted without; it is rejected if it still exceeds the threshold against that fit. Rejected
    points keep their residual against the final fit; nothing is dropped silently.
    """
    p = _check_points(points_mm, MIN_POINTS_FIXED_RADIUS)
    inliers = np.ones(len(p), dtype=bool)
    fit = fit_sphere(p, radius_mm, initial_centre_mm)
    while True:
        res = np.linalg.norm(p - fit.centre_mm, axis=1) - radius_mm
        candidates = np.where(inliers, np.abs(res), -np.inf)
        worst = int(np.argmax(candidates))
        if candidates[worst] <= threshold_mm or inliers.sum() <= MIN_POINTS_FIXED_RADIUS:
            break
        trial = inliers.copy()
        trial[worst] = False
        trial_fit = fit_sphere(p[trial], radius_mm, fit.centre_mm)
        if abs(np.linalg.norm(p[worst] - trial_fit.centre_mm) - radius_mm) <= threshold_mm:
            break
        inliers, fit = trial, trial_fit
    res = np.linalg.norm(p - fit.centre_mm, axis=1) - radius_mm
    return RobustSphereFit(fit=fit, inliers=inliers, residuals_mm=res, threshold_mm=float(threshold_mm))


def _orthonormal_basis(up: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    z = np.asarray(up, dtype=float)
    norm = np.linalg.norm(z)
    if z.shape != (3,) or not np.isfinite(norm) or norm == 0:
        raise ValueError(f"up must be a finite non-zero 3-vector, got {up!r}")
    z = z / norm
    helper = np.array([1.0, 0.0, 0.0]) if abs(z[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    x = np.cross(helper, z)
    x /= np.linalg.norm(x)
    return x, np.cross(z, x), z


def sphere_probe_pattern(
    centre_mm: np.ndarray,
    radius_mm: float,
    up: np.ndarray = (0.0, 0.0, 1.0),
    n_ring: int = 6,
    elevations_deg: tuple[float, ...] = (30.0,),
) -> tuple[np.ndarray, np.ndarray]:
    """Nominal touch points and outward unit normals: the pole along ``up`` plus rings at the elevations.

    Elevation is measured from the sphere's equator (0) towards the pole (90); successive rings are
    staggered by half the azimuth step. Returns (targets (N, 3), normals (N, 3)), N = 1 + n_ring * rings.
    """
    if n_ring < 3:
        raise ValueError(f"n_ring must be at least 3, got {n_ring}")
    x, y, z = _orthonormal_basis(np.asarray(up, dtype=float))
    normals = [z]
    for k, elevation in enumerate(elevations_deg):
        if not -90.0 < elevation < 90.0:
            raise ValueError(f"elevations must lie inside (-90, 90) degrees, got {elevation}")
        el = np.radians(elevation)
        az = 2.0 * np.pi * (np.arange(n_ring) + 0.5 * (k % 2)) / n_ring
        for a in az:
            normals.append(np.cos(el) * (np.cos(a) * x + np.sin(a) * y) + np.sin(el) * z)
    n = np.array(normals)
    return np.asarray(centre_mm, dtype=float) + radius_mm * n, n
