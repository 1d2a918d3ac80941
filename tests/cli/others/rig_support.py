"""The simulated rig behind a controller the tests did not write the driver for: what an instrument sees of it.

A device on python-can's virtual bus moves the rig from its own thread while an instrument's server reads it from
another, so both go through one lock. The platform's tooling spheres in the instrument's frame are computed here
from the rig's true pose and the robot file's sphere layout, for a CMM server that knows nothing of the rig.
"""

from __future__ import annotations

import threading

import numpy as np

from hilcal.kinematics import split_pose
from hilcal.robot import Robot
from sim_devices.rig.rig import SimulatedRig


class RigView:
    """The rig as the CMM sees it, read under the lock the controller moves it with."""

    def __init__(self, rig: SimulatedRig, lock: threading.Lock) -> None:
        self._rig, self._lock = rig, lock

    def true_pose(self) -> np.ndarray:
        with self._lock:
            return self._rig.true_pose()

    def to_cmm(self, points_base_mm: np.ndarray) -> np.ndarray:
        return self._rig.to_cmm(points_base_mm)

    def spheres_in_cmm(self, robot: Robot) -> list[tuple[tuple[float, float, float], float]]:
        """The three platform and three base tooling spheres as (centre in the CMM frame, radius), both mm."""
        R, t = split_pose(self.true_pose()[None, :])
        platform = robot.platform_spheres @ R[0].T + t[0]
        centres = self.to_cmm(np.vstack([platform, robot.base_spheres]))
        return [(tuple(float(v) for v in c), robot.sphere_radius_mm) for c in centres]
