"""Instrument stations as unknowns of the fit: every set-up of a tracker or CMM (or a logged file's frame) has its own
small rigid error, fitted together with the geometry and the effects (a bundle adjustment).

A row's measured pose is the true pose seen through its station's registration: measured = dX_s o true, dX_s a small
rigid motion (dt, dw) about the workspace centre c, in base axes. In the residual metric of
``hilcal.error_models.pose_difference`` ([t_m - t_p (mm), length_mm rotvec(R_m R_p^T)]) a row's residual grows by
A_i [dt; dw] with A_i = [[I, -[t_i - c]x], [0, length_mm I]]. The first station (in row order) fixes the gauge: the
base frame is the one its registration gives, so its dX is zero; every other station's six unknowns are eliminated
from the least squares by projecting residuals and Jacobians onto the complement of its columns (Frisch-Waugh-Lovell:
the other parameters' estimates and covariance are those of the joint fit, for these linearised frames). A station
seen in one pose only carries no information on the rest and is projected out whole.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from hilcal.kinematics import split_pose


def _skew(v: np.ndarray) -> np.ndarray:
    S = np.zeros((*v.shape, 3))
    S[..., 0, 1], S[..., 0, 2] = -v[..., 2], v[..., 1]
    S[..., 1, 0], S[..., 1, 2] = v[..., 2], -v[..., 0]
    S[..., 2, 0], S[..., 2, 1] = -v[..., 1], v[..., 0]
    return S


def station_columns(poses: np.ndarray, length_mm: float, centre_mm: np.ndarray) -> np.ndarray:
    """(N, 6, 6): d(pose residual of each row)/d[dt (mm); dw (rad)] of its station's rigid error."""
    _, t = split_pose(np.atleast_2d(poses))
    A = np.zeros((len(t), 6, 6))
    A[:, :3, :3] = np.eye(3)
    A[:, :3, 3:] = -_skew(t - np.asarray(centre_mm, dtype=float))
    A[:, 3:, 3:] = length_mm * np.eye(3)
    return A


@dataclass(frozen=True)
class StationFrames:
    """The free stations of some rows and how to eliminate or estimate their rigid errors (see module docstring)."""

    labels: np.ndarray
    """(N,) each row's station."""
    free: tuple[int, ...]
    """The stations whose frame is fitted (every one but the reference)."""
    reference: int
    columns: np.ndarray
    """(N, 6, 6) the rows' station columns (``station_columns``)."""

    @classmethod
    def of(cls, stations: np.ndarray, poses: np.ndarray, length_mm: float, centre_mm: np.ndarray
           ) -> StationFrames | None:
        """The frames of these rows' stations; None when they all share one station (nothing to fit)."""
        labels = np.asarray(stations).astype(int)
        order = list(dict.fromkeys(labels.tolist()))
        if len(order) < 2:
            return None
        return cls(labels, tuple(order[1:]), order[0], station_columns(poses, length_mm, centre_mm))

    @property
    def n_params(self) -> int:
        return 6 * len(self.free)

    def _blocks(self) -> list[tuple[np.ndarray, np.ndarray]]:
        """Per free station: its rows' indices into the stacked residual (6 per row) and its columns there."""
        out = []
        for s in self.free:
            rows = np.flatnonzero(self.labels == s)
            idx = (6 * rows[:, None] + np.arange(6)).ravel()
            out.append((idx, self.columns[rows].reshape(-1, 6)))
        return out

    def project(self, r: np.ndarray, J: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray | None]:
        """Residuals (N*6,) and Jacobian (N*6, p) with every free station's columns projected out."""
        r = np.array(r, dtype=float, copy=True)
        J = None if J is None else np.array(J, dtype=float, copy=True)
        for idx, A in self._blocks():
            Q, _ = np.linalg.qr(A)
            r[idx] -= Q @ (Q.T @ r[idx])
            if J is not None:
                J[idx] -= Q @ (Q.T @ J[idx])
        return r, J

    def estimate(self, r: np.ndarray) -> dict[int, np.ndarray]:
        """Each free station's rigid error [dt (mm); dw (rad)] from the rows' (unprojected) residuals (N*6,)."""
        return {s: np.linalg.lstsq(A, np.asarray(r, dtype=float)[idx], rcond=None)[0]
                for s, (idx, A) in zip(self.free, self._blocks(), strict=True)}


def remove_frames(poses: np.ndarray, stations: np.ndarray, frames: dict[int, np.ndarray], length_mm: float,
                  centre_mm: np.ndarray) -> np.ndarray:
    """Poses (N, 6: mm, deg) with each row's station error taken out to first order: the residual offset A_i dX of
    the row's station is subtracted (``pose_difference`` units), as predictions in the base frame need."""
    q = np.array(np.atleast_2d(poses), dtype=float, copy=True)
    A = station_columns(q, length_mm, centre_mm)
    labels = np.asarray(stations).astype(int)
    for s, dx in frames.items():
        rows = labels == s
        delta = A[rows] @ dx
        q[rows, :3] -= delta[:, :3]
        q[rows, 3:] = _rotate_back(q[rows], delta[:, 3:] / length_mm)
    return q


def _rotate_back(poses: np.ndarray, dw: np.ndarray) -> np.ndarray:
    """roll, pitch, yaw (deg) of the rotations turned back by small rotation vectors dw (rad, base axes)."""
    from scipy.spatial.transform import Rotation

    R, _ = split_pose(poses)
    back = Rotation.from_rotvec(-dw).as_matrix() @ R
    ypr = Rotation.from_matrix(back).as_euler("ZYX", degrees=True)
    return np.column_stack([ypr[:, 2], ypr[:, 1], ypr[:, 0]])
