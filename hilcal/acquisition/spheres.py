"""Where a rigid body's tooling spheres are expected, how sure that is, and what each measured sphere teaches.

A body (the base, or the platform) is a frame T (rotation R, translation t) with a Gaussian uncertainty of
[dt (mm); dw (rad)]: p' = (I + [dw]x) R s + t + dt for a body point s, dw the small rotation about the body's origin
in the parent's axes. A measured sphere centre conditions the frame (a Kalman update), so the next sphere of the
same body is searched for in a smaller region: after one sphere the translation is known, after two nearly all.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass

import numpy as np

from hilcal.robot import Robot, rotation_matrix

COVERAGE_K = 4.0
"""A prediction's bound is this many standard deviations along its worst direction (4 sigma in 3-D: the true centre
lies outside with a probability of about 1e-3)."""


def _skew(v: np.ndarray) -> np.ndarray:
    return np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])


def _rotation(w: np.ndarray) -> np.ndarray:
    """Rotation matrix of a rotation vector (rad), Rodrigues."""
    angle = float(np.linalg.norm(w))
    if angle < 1e-15:
        return np.eye(3) + _skew(w)
    k = _skew(w / angle)
    return np.eye(3) + np.sin(angle) * k + (1.0 - np.cos(angle)) * (k @ k)


@dataclass(frozen=True)
class SpherePrediction:
    """A sphere centre the instrument should find: where, how far it may be off (a bound, mm), and its pole."""

    centre_mm: np.ndarray
    bound_mm: float
    up: np.ndarray
    """Unit direction away from the sphere's mount, the side a probe may come from."""
    ceiling_mm: float = 0.0
    """A search starts at least this far above the prediction (besides the bound): a frame that is not known to
    its tolerance yet (the station's alignment before it is registered) may put the sphere higher than its bound."""


@dataclass(frozen=True)
class BodyBelief:
    """A rigid frame in its parent (4x4 ``T``) and the covariance (6, 6) of [dt (mm); dw (rad)]."""

    T: np.ndarray
    cov: np.ndarray

    @classmethod
    def within(cls, T: np.ndarray, tolerance_mm: float, tolerance_deg: float) -> BodyBelief:
        """A frame known to a tolerance (a bound, read as COVERAGE_K standard deviations per axis)."""
        sd = np.array([tolerance_mm] * 3 + [np.radians(tolerance_deg)] * 3) / COVERAGE_K
        return cls(np.asarray(T, dtype=float), np.diag(sd**2))

    def _jacobian(self, body_point: np.ndarray) -> np.ndarray:
        """d(point in the parent)/d[dt; dw] (3, 6)."""
        lever = self.T[:3, :3] @ np.asarray(body_point, dtype=float)
        return np.hstack([np.eye(3), -_skew(lever)])

    def point(self, body_point: np.ndarray) -> np.ndarray:
        """The body point in the parent frame."""
        return self.T[:3, :3] @ np.asarray(body_point, dtype=float) + self.T[:3, 3]

    def point_cov(self, body_point: np.ndarray) -> np.ndarray:
        """(3, 3) covariance of the body point in the parent frame."""
        H = self._jacobian(body_point)
        return H @ self.cov @ H.T

    def predict(self, body_point: np.ndarray, up_body: np.ndarray, floor_mm: float) -> SpherePrediction:
        """The sphere at `body_point` with its bound: COVERAGE_K standard deviations along the worst direction,
        at least `floor_mm`."""
        worst = float(np.sqrt(max(np.max(np.linalg.eigvalsh(self.point_cov(body_point))), 0.0)))
        up = self.T[:3, :3] @ np.asarray(up_body, dtype=float)
        return SpherePrediction(self.point(body_point), max(COVERAGE_K * worst, floor_mm), up / np.linalg.norm(up))

    def condition(self, body_point: np.ndarray, measured_mm: np.ndarray, sigma_mm: float) -> BodyBelief:
        """The frame after the sphere at `body_point` was measured at `measured_mm` (noise `sigma_mm` per axis)."""
        H = self._jacobian(body_point)
        S = H @ self.cov @ H.T + sigma_mm**2 * np.eye(3)
        K = np.linalg.solve(S, H @ self.cov).T
        xi = K @ (np.asarray(measured_mm, dtype=float) - self.point(body_point))
        T = np.eye(4)
        T[:3, :3] = _rotation(xi[3:]) @ self.T[:3, :3]
        T[:3, 3] = self.T[:3, 3] + xi[:3]
        cov = (np.eye(6) - K @ H) @ self.cov
        return BodyBelief(T, 0.5 * (cov + cov.T))

    def composed(self, T_child: np.ndarray, child_cov: np.ndarray) -> BodyBelief:
        """A child frame T_child (in this body's frame) with its own covariance (in this body's axes), in the
        parent: the platform in the CMM frame from the base's registration and the predicted pose."""
        R = self.T[:3, :3]
        T = self.T @ T_child
        # The child's translation and rotation errors, rotated into the parent's axes; the parent's own error moves
        # the child's origin by dt + dw x (R t_child) and turns it by dw.
        rot = np.zeros((6, 6))
        rot[:3, :3] = R
        rot[3:, 3:] = R
        lever = np.zeros((6, 6))
        lever[:3, :3] = np.eye(3)
        lever[:3, 3:] = -_skew(R @ T_child[:3, 3])
        lever[3:, 3:] = np.eye(3)
        cov = rot @ child_cov @ rot.T + lever @ self.cov @ lever.T
        return BodyBelief(T, 0.5 * (cov + cov.T))


def park_height_mm(robot: Robot, clearance_mm: float) -> float:
    """A height (base z, mm) above every place a platform sphere can reach in the workspace, by `clearance_mm`: where
    the probe waits while the platform moves (a probe left beside a platform sphere would be struck by it)."""
    bounds = robot.workspace
    corners = np.array(list(itertools.product(*bounds)))
    R = rotation_matrix(np.radians(corners[:, 3:]))
    tops = np.einsum("nij,kj->nki", R, robot.platform_spheres)[..., 2] + corners[:, None, 2]
    return float(np.max(tops)) + robot.sphere_radius_mm + clearance_mm
