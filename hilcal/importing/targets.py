"""The platform pose from raw target points (laser tracker, CMM), by the same rigid registration as the CMM path.

Each row's platform targets, measured in the instrument's frame, are registered onto their known positions on
the platform (least squares, ``hilcal.pose_measurement.rigid_fit``). With base targets the instrument's frame is
registered too and cancels, as with the CMM's base spheres; without them the points are taken to be in the base
frame already. The fit residual is the recording's ``sphere_fit_rms_mm``: the larger RMS of the registrations.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from hilcal.importing.errors import ValueProblem
from hilcal.pose_measurement import pose_from_matrix, rigid_fit

MAX_FIT_RMS_FRACTION = 0.01
"""A registration RMS above this fraction of the layout's RMS radius is not measurement noise: a unit that does not
fit, a target in the wrong column or a wrong position in the map."""


@dataclass(frozen=True)
class TargetFit:
    """Poses registered from target points, and the quality of each registration."""

    pose: np.ndarray
    """(n, 6) [x, y, z mm, roll, pitch, yaw deg] of the platform frame in the base frame."""
    rms_mm: np.ndarray
    """(n,) the larger RMS residual of the platform and base registrations (``sphere_fit_rms_mm``)."""
    platform_rms_mm: np.ndarray
    base_rms_mm: np.ndarray | None


def _residuals(R: np.ndarray, t: np.ndarray, layout: np.ndarray, measured: np.ndarray) -> np.ndarray:
    """(n, K) distance of every measured point from its registered layout point."""
    fitted = np.einsum("nij,kj->nki", R, layout) + t[:, None, :]
    return np.linalg.norm(fitted - measured, axis=2)


def _check(residual: np.ndarray, layout: np.ndarray, offset: int, body: str) -> None:
    """Raise at the worst target of the first row whose registration does not fit the layout."""
    radius = float(np.sqrt(np.mean(np.sum((layout - layout.mean(axis=0)) ** 2, axis=1))))
    limit = MAX_FIT_RMS_FRACTION * radius
    rms = np.sqrt(np.mean(residual**2, axis=1))
    bad = rms > limit
    if np.any(bad):
        i = int(np.argmax(bad))
        k = int(np.argmax(residual[i]))
        raise ValueProblem(i, offset + k, f"the {body} targets do not fit their layout in the map: registration RMS "
                           f"{rms[i]:.4g} mm (this target {residual[i, k]:.4g} mm off), more than "
                           f"{MAX_FIT_RMS_FRACTION:.0%} of the layout's {radius:.4g} mm radius: check the unit, the "
                           "columns of each target and their position_mm")


def register_targets(
    platform_mm: np.ndarray, platform_layout: np.ndarray,
    base_mm: np.ndarray | None = None, base_layout: np.ndarray | None = None,
) -> TargetFit:
    """Poses from (n, K, 3) platform targets and optionally (n, M, 3) base targets, all in mm.

    A ValueProblem names the row and the target (platform targets first, then base targets) of a fit that is
    not noise.
    """
    P = np.asarray(platform_mm, dtype=float)
    layout_p = np.asarray(platform_layout, dtype=float)
    R_p, t_p, rms_p = rigid_fit(layout_p, P)
    _check(_residuals(R_p, t_p, layout_p, P), layout_p, 0, "platform")
    if base_mm is None or base_layout is None:
        return TargetFit(pose=pose_from_matrix(R_p, t_p), rms_mm=rms_p, platform_rms_mm=rms_p, base_rms_mm=None)
    B = np.asarray(base_mm, dtype=float)
    layout_b = np.asarray(base_layout, dtype=float)
    R_b, t_b, rms_b = rigid_fit(layout_b, B)
    _check(_residuals(R_b, t_b, layout_b, B), layout_b, len(layout_p), "base")
    R_bT = np.swapaxes(R_b, 1, 2)
    R = R_bT @ R_p
    t = np.einsum("nij,nj->ni", R_bT, t_p - t_b)
    return TargetFit(pose=pose_from_matrix(R, t), rms_mm=np.maximum(rms_p, rms_b), platform_rms_mm=rms_p,
                     base_rms_mm=rms_b)
