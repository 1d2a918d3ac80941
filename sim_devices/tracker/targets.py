"""Where the simulated tracker's reflectors are: a callable that gives their true centres now, (N, 3) mm in the base
frame. ``rig_reflectors`` puts one on each of the rig's tooling spheres (the robot file's layouts: the platform's
moving with ``rig.true_pose()``, then the base's); a station with other targets passes its own callable.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Protocol

import numpy as np
from scipy.spatial.transform import Rotation

from hilcal.robot import Robot


class PoseSource(Protocol):
    def true_pose(self) -> np.ndarray: ...


def rig_reflectors(robot: Robot, rig: PoseSource) -> Callable[[], np.ndarray]:
    """Reflectors at the robot file's sphere centres: platform spheres (moved by the rig's true pose [x, y, z mm,
    roll, pitch, yaw deg], R = Rz Ry Rx) first, then base spheres."""
    platform, base = robot.platform_spheres, robot.base_spheres

    def centres() -> np.ndarray:
        pose = rig.true_pose()
        moved = Rotation.from_euler("ZYX", pose[[5, 4, 3]], degrees=True).apply(platform) + pose[:3]
        return np.vstack([moved, base])

    return centres

