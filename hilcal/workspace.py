"""The reachable workspace: which poses a robot can take (box, leg limits, distance from singularity) and
uniform random poses among them. Used by pose design, by the diagnosis' extra poses and by the simulations.

Poses are arrays [..., 6] = [x, y, z (mm), roll, pitch, yaw (deg)].
"""

from __future__ import annotations

import numpy as np

from hilcal.kinematics import Geometry, inverse_jacobian, inverse_kinematics, scaled_condition, split_pose
from hilcal.robot import Robot

MAX_CONDITION = 1e3
"""Largest scaled inverse-Jacobian condition number of a usable pose (far from singular)."""


def feasible(robot: Robot, poses: np.ndarray, *, max_condition: float = MAX_CONDITION) -> np.ndarray:
    """Boolean mask [...]: inside the workspace box, nominal legs within limits, and far from singular."""
    q = np.asarray(poses, dtype=float)
    ws = robot.workspace
    in_box = np.all((q >= ws[:, 0]) & (q <= ws[:, 1]), axis=-1)
    geom = Geometry.nominal(robot)
    lengths = inverse_kinematics(geom, q)
    lo, hi = robot.leg_limits
    legs_ok = np.all((lengths >= lo) & (lengths <= hi), axis=-1)
    R, t = split_pose(q)
    cond = scaled_condition(inverse_jacobian(geom, R, t), robot.characteristic_length_mm)
    return in_box & legs_ok & (cond < max_condition)


def random_poses(robot: Robot, n: int, rng: np.random.Generator, *, max_draws: int = 1_000_000) -> np.ndarray:
    """n poses (n, 6) uniform over the feasible part of the workspace box (vectorized rejection sampling)."""
    if n < 0:
        raise ValueError(f"n must be non-negative, got {n}")
    ws = robot.workspace
    kept: list[np.ndarray] = []
    count = drawn = 0
    batch = max(64, 2 * n)
    while count < n:
        if drawn >= max_draws:
            raise ValueError(
                f"only {count} feasible poses in {drawn} uniform draws: the workspace box is (almost) all "
                "outside the leg limits or near singularities"
            )
        q = ws[:, 0] + rng.random((batch, 6)) * (ws[:, 1] - ws[:, 0])
        ok = q[feasible(robot, q)]
        kept.append(ok)
        count += len(ok)
        drawn += batch
        if drawn and count:
            batch = int(min(max_draws, max(64, 1.2 * (n - count) * drawn / count)))
    return np.concatenate(kept)[:n] if kept else np.empty((0, 6))
