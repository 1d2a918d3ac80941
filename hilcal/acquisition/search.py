"""The geometry of a sphere search, as a CMM operator does it: descend onto the sphere from above on a widening
pattern until a touch, touch around that point, and solve the centre from the touched cap.

A vertical descent (along the sphere's ``up``) hits a sphere of radius r when it passes within r of its centre, and
its first touch lies on the upper hemisphere. Descents on a hexagonal lattice of spacing 0.8 sqrt(3) r leave no point
farther than 0.8 r from a descent, so a sphere whose centre lies within the searched disk cannot be missed.
"""

from __future__ import annotations

import numpy as np

LATTICE_FILL = 0.8
"""The lattice's covering radius as a fraction of the sphere's radius."""
CAP_STEP = 0.5
"""Descents around the first touch, this fraction of the radius away from it."""
MAX_ITERATIONS = 30


def basis(up: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Two unit directions across `up` and `up` itself (unit)."""
    z = np.asarray(up, dtype=float)
    z = z / np.linalg.norm(z)
    helper = np.array([1.0, 0.0, 0.0]) if abs(z[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    x = np.cross(helper, z)
    x /= np.linalg.norm(x)
    return x, np.cross(z, x), z


def descent_offsets(radius_mm: float, reach_mm: float) -> np.ndarray:
    """(N, 2) lateral offsets of descents that cover a disk of `reach_mm` around the prediction, nearest first."""
    spacing = LATTICE_FILL * np.sqrt(3.0) * radius_mm
    n = int(np.ceil((reach_mm + radius_mm) / spacing)) + 1
    i, j = np.meshgrid(np.arange(-n, n + 1), np.arange(-n, n + 1))
    points = np.column_stack([(i + 0.5 * j).ravel(), (np.sqrt(3.0) / 2.0 * j).ravel()]) * spacing
    d = np.linalg.norm(points, axis=1)
    cover = reach_mm + LATTICE_FILL * radius_mm
    keep = d <= cover
    order = np.lexsort((np.arctan2(points[keep, 1], points[keep, 0]), d[keep]))
    return points[keep][order]


def cap_offsets(radius_mm: float) -> np.ndarray:
    """(6, 2) lateral offsets, from the first touch, of the descents that find more of the cap around it."""
    angles = np.arange(6) * np.pi / 3.0
    return CAP_STEP * radius_mm * np.column_stack([np.cos(angles), np.sin(angles)])


def cap_centre(points_mm: np.ndarray, radius_mm: float, up: np.ndarray) -> tuple[np.ndarray, float]:
    """The centre of a sphere of known radius through touches on its upper cap (at least 3, not on one line), and
    the RMS radial residual. The centre lies below the touches (against `up`): the solution on that side."""
    p = np.asarray(points_mm, dtype=float)
    if len(p) < 3:
        raise ValueError(f"a sphere of known radius needs 3 touches, got {len(p)}")
    z = np.asarray(up, dtype=float) / np.linalg.norm(up)
    c = p.mean(axis=0) - radius_mm * z
    for _ in range(MAX_ITERATIONS):
        d = p - c
        dist = np.linalg.norm(d, axis=1)
        r = dist - radius_mm
        J = -d / dist[:, None]
        step = np.linalg.lstsq(J, -r, rcond=None)[0]
        c = c + step
        if np.linalg.norm(step) < 1e-9:
            break
    residual = np.linalg.norm(p - c, axis=1) - radius_mm
    if np.min((p - c) @ z) < -1e-6 * radius_mm:
        raise ValueError("the touches are not on one sphere's upper cap")
    return c, float(np.sqrt(np.mean(residual**2)))
