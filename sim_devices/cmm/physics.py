"""Geometry of the simulated CMM's world: the rig's six tooling spheres in the CMM frame and a stylus ball among them.

The platform spheres move with ``rig.true_pose()``, the base spheres do not; ``rig.to_cmm`` maps them into the CMM
frame. The stylus is a ball of radius r whose centre is the machine's position: it meets a sphere of radius R where
its centre comes to R + r from the sphere's centre (a point probe is r = 0). ``Spheres`` answers where a straight move
of the ball first meets a sphere, whether a point is inside one, and whether the platform, moving since the machine
last looked, carried a sphere through the parked ball (the poses between interpolated: translation straight,
orientation by slerp).
"""

from __future__ import annotations

import numpy as np

from hilcal.robot import Robot
from sim_devices.rig.rig import SimulatedRig
from sim_devices.rotation import matrix_from_rpy_deg, rotvec_from_matrix, slerp

PENETRATION_TOL_MM = 1e-6
"""A move enters a sphere when the ball's centre comes closer to the sphere's centre than R + r less this (a ball
stopped on a surface may leave it, or move along it)."""
WAY_STEP_DEG = 0.5
"""The platform's way between two looks is sampled every this much turn (a sphere 1 m out then strays at most 10 µm
from the straight steps between the samples)."""
MAX_WAY_STEPS = 512


def sphere_name(index: int) -> str:
    """How the log names sphere ``index`` of ``Spheres.centres_mm`` (platform spheres first)."""
    return f"platform sphere {index + 1}" if index < 3 else f"base sphere {index - 2}"


class Spheres:
    """The tooling spheres as the CMM sees them; the last platform pose looked at is remembered."""

    def __init__(self, robot: Robot, rig: SimulatedRig) -> None:
        self.robot = robot
        self.rig = rig
        self.radius_mm = robot.sphere_radius_mm
        self._seen: tuple[bytes, np.ndarray, np.ndarray] | None = None
        """The platform pose last looked at (as bytes), the sphere centres for it, and the pose."""

    def look(self) -> tuple[np.ndarray, np.ndarray | None]:
        """(6, 3) true sphere centres in the CMM frame (platform spheres first) and, when the platform moved since
        the last look, its way: (n + 1, 3, 3) platform sphere centres along it; None when it did not move."""
        pose = self.rig.true_pose()
        key = pose.tobytes()
        if self._seen is not None and self._seen[0] == key:
            return self._seen[1].copy(), None
        platform = self.robot.platform_spheres @ matrix_from_rpy_deg(pose[3:]).T + pose[:3]
        previous = self._seen
        self._seen = (key, self.rig.to_cmm(np.vstack([platform, self.robot.base_spheres])), pose)
        way = None if previous is None else self._platform_way(previous[2], pose)
        return self._seen[1].copy(), way

    def centres_mm(self) -> np.ndarray:
        return self.look()[0]

    def _platform_way(self, pose0: np.ndarray, pose1: np.ndarray) -> np.ndarray:
        R0, R1 = matrix_from_rpy_deg(pose0[3:]), matrix_from_rpy_deg(pose1[3:])
        turn_deg = float(np.degrees(np.linalg.norm(rotvec_from_matrix(R0.T @ R1))))
        n = int(min(MAX_WAY_STEPS, max(1, np.ceil(turn_deg / WAY_STEP_DEG))))
        t = np.linspace(0.0, 1.0, n + 1)
        R = slerp(R0, R1, t)
        shift = pose0[:3] + t[:, None] * (pose1[:3] - pose0[:3])
        points = np.einsum("nij,kj->nki", R, self.robot.platform_spheres) + shift[:, None, :]
        return self.rig.to_cmm(points.reshape(-1, 3)).reshape(points.shape)

    def strikes(self, way: np.ndarray, ball_mm: np.ndarray, ball_radius_mm: float) -> list[tuple[int, np.ndarray]]:
        """The platform spheres that, carried along ``way``, came closer to the ball's centre than R + r on one of
        the straight steps between the samples: (index, the sphere's centre at the end). A ball already inside a
        sphere's old place is not struck again."""
        reach = self.radius_mm + ball_radius_mm
        out = []
        for index in range(way.shape[1]):
            a, b = way[:-1, index], way[1:, index]
            if np.linalg.norm(ball_mm - a[0]) < reach - PENETRATION_TOL_MM:
                continue
            d = b - a
            t = np.clip(np.sum((ball_mm - a) * d, axis=1) / np.maximum(np.sum(d * d, axis=1), 1e-300), 0.0, 1.0)
            if np.min(np.linalg.norm(a + t[:, None] * d - ball_mm, axis=1)) < reach - PENETRATION_TOL_MM:
                out.append((index, b[-1]))
        return out

    def first_contact(self, start: np.ndarray, end: np.ndarray, ball_radius_mm: float,
                      centres: np.ndarray | None = None) -> tuple[int, np.ndarray] | None:
        """The first sphere the ball, its centre moving straight from start to end, enters: (index, the ball's
        centre where it meets the surface), or None when the move stays clear. A start inside meets it at once.
        ``centres``: the spheres as a look at the platform gave them (default: look now)."""
        centres = self.centres_mm() if centres is None else centres
        reach = self.radius_mm + ball_radius_mm
        d = end - start
        m = start - centres
        a = float(d @ d)
        if a == 0.0:
            closest = np.linalg.norm(m, axis=1)
            entry = np.zeros(len(centres))
        else:
            b = m @ d
            closest = np.linalg.norm(m + np.clip(-b / a, 0.0, 1.0)[:, None] * d, axis=1)
            c = np.sum(m * m, axis=1) - reach * reach
            with np.errstate(invalid="ignore"):
                entry = np.maximum((-b - np.sqrt(np.maximum(b * b - a * c, 0.0))) / a, 0.0)
        hit = closest < reach - PENETRATION_TOL_MM
        if not hit.any():
            return None
        index = int(np.argmin(np.where(hit, entry, np.inf)))
        return index, start + min(float(entry[index]), 1.0) * d

    def inside(self, point: np.ndarray, ball_radius_mm: float, centres: np.ndarray | None = None) -> int | None:
        """The sphere the ball would overlap with its centre at ``point``, or None."""
        centres = self.centres_mm() if centres is None else centres
        gaps = np.linalg.norm(point - centres, axis=1) - (self.radius_mm + ball_radius_mm)
        index = int(np.argmin(gaps))
        return index if gaps[index] < -PENETRATION_TOL_MM else None

    def touch(self, start: np.ndarray, direction: np.ndarray, stroke_mm: float, ball_radius_mm: float,
              centres: np.ndarray | None = None) -> tuple[int, float] | None:
        """The ball moving from ``start`` along the unit ``direction`` for up to ``stroke_mm``: (sphere, distance
        travelled) where it first touches a sphere, or None."""
        reach = self.radius_mm + ball_radius_mm
        m = start - (self.centres_mm() if centres is None else centres)
        b = m @ direction
        c = np.sum(m * m, axis=1) - reach * reach
        disc = b * b - c
        with np.errstate(invalid="ignore"):
            s = np.where(disc >= 0, -b - np.sqrt(np.maximum(disc, 0.0)), np.inf)
        s = np.where((s >= 0) & (s <= stroke_mm), s, np.inf)
        index = int(np.argmin(s))
        return None if not np.isfinite(s[index]) else (index, float(s[index]))
