"""Poses for tests, drawn here rather than with hilcal's own sampler, so a test does not lean on the code under
test to make its inputs."""

from __future__ import annotations

from functools import lru_cache

import numpy as np

from hilcal.kinematics import Geometry, inverse_kinematics
from hilcal.robot import Robot


def feasible_random_poses(robot: Robot, n: int, rng: np.random.Generator) -> np.ndarray:
    """Uniform workspace poses whose nominal leg lengths respect the limits (written here, not in hilcal)."""
    ws = robot.workspace
    lo, hi = robot.leg_limits
    out = np.empty((0, 6))
    while len(out) < n:
        q = rng.uniform(ws[:, 0], ws[:, 1], size=(4 * n, 6))
        L = inverse_kinematics(Geometry.nominal(robot), q)
        out = np.concatenate([out, q[((L > lo) & (L < hi)).all(axis=1)]])
    return out[:n]


@lru_cache(maxsize=8)
def _designed(n: int, seed: int) -> np.ndarray:
    from hilcal.planning.design import factorial_exchange
    from hilcal.robot import default_robot

    poses = factorial_exchange(default_robot(), n, np.random.default_rng(seed)).poses
    poses.setflags(write=False)
    return poses


def default_design(n: int, seed: int) -> np.ndarray:
    """The default robot's D-optimal measure poses (hilcal's design, seeded), made once per test process: the
    discovery and end-to-end tests measure on the plan a run would use, and designing it takes about 1.5 s."""
    return _designed(n, seed)
