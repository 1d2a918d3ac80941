"""Where the simulated tracker's reflectors are: a callable that gives their true centres now, (N, 3) mm in the base
frame. ``layout_reflectors`` puts one in each nest of a station's target layouts (platform targets in the platform
frame, moving with ``rig.true_pose()``, then the base monuments); ``default_targets`` derives such layouts from a robot
file (four platform nests and four base monuments around its tooling spheres); ``rig_reflectors`` puts one on each of
the rig's tooling spheres.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Protocol

import numpy as np

from hilcal.robot import Robot
from sim_devices.rotation import matrix_from_rpy_deg


class PoseSource(Protocol):
    def true_pose(self) -> np.ndarray: ...


def default_targets(robot: Robot) -> tuple[np.ndarray, np.ndarray]:
    """Four platform nests (platform frame) and four base monuments (base frame), mm: at the robot file's three
    platform and three base sphere centres, each layout with a fourth opposite its first sphere across the layout's
    centre (as far from the centre as that sphere)."""
    return _with_fourth(robot.platform_spheres), _with_fourth(robot.base_spheres)


def _with_fourth(points: np.ndarray) -> np.ndarray:
    centre = points.mean(axis=0)
    return np.vstack([points, 2.0 * centre - points[0]])


def rig_reflectors(robot: Robot, rig: PoseSource) -> Callable[[], np.ndarray]:
    """Reflectors at the robot file's sphere centres: platform spheres (moved by the rig's true pose [x, y, z mm,
    roll, pitch, yaw deg], R = Rz Ry Rx) first, then base spheres."""
    return layout_reflectors(robot.platform_spheres, robot.base_spheres, rig)


def layout_reflectors(platform_mm: np.ndarray, base_mm: np.ndarray, rig: PoseSource) -> Callable[[], np.ndarray]:
    """Reflectors in the nests of target layouts: the platform's (platform frame, moved by the rig's true pose) first,
    then the base's (base frame)."""
    platform, base = np.asarray(platform_mm, dtype=float), np.asarray(base_mm, dtype=float)

    def centres() -> np.ndarray:
        pose = rig.true_pose()
        moved = platform @ matrix_from_rpy_deg(pose[3:]).T + pose[:3]
        return np.vstack([moved, base])

    return centres

