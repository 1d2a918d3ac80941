"""Candidate poses for a sequential (adaptive) calibration plan, and what each one tells about the library physics.

A sequential plan picks its next pose from a fixed, seeded candidate set, so a resumed run that replays the same
measurements sees the same candidates. The set is the union of the feasible points of the 3-level full factorial
over the workspace box (its corners are D-optimal-like), poses on the boundary of the feasible region (random
directions from home pushed outwards by bisection until the box, a leg limit or the singularity bound stops them:
information grows towards the boundary, which a grid only reaches at its nodes), uniform random feasible poses,
and optionally the poses of a reference design. Every candidate is feasible for the robot with its lower leg
limit raised by the approach distance plus 1 mm, as ``procedures.plan.make_plan`` designs.

The library variables are what the missing-physics diagnosis needs spread in: the axial load of each leg from the
platform's weight (kN, compression positive; compliances) and each leg's stroke (m; scale errors, oil columns).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from hilcal.kinematics import Geometry, gravity_wrench, inverse_kinematics, leg_forces
from hilcal.planning.design import factorial_candidates, pose_jacobians
from hilcal.robot import LegLimitSpec, Robot
from hilcal.workspace import feasible, random_poses

BISECTION_STEPS = 30
"""Bisection steps along a ray: 2^-30 of the ray, far below a µm."""
DESIGN_MARGIN_MM = 1.0
"""Extra room above the approach point's legs, as the fixed plan is designed."""


@dataclass(frozen=True)
class CandidateSet:
    """Candidate poses (C, 6) in mm and degrees, with their nominal pose-error Jacobians and library variables.

    jacobians [C, 6, 42]: pose-error Jacobians at the nominal geometry (rotation rows in mm at the characteristic
    length). library [C, 6, 12]: the pose change per unit of each library term (6 load terms, per kN on one leg;
    6 stroke terms, per m on one leg), i.e. the leg-length column of the Jacobian times the variable. load_kn and
    stroke_m [C, 6] per leg. source [C]: "factorial", "boundary", "random" or "reference".
    """

    poses: np.ndarray
    jacobians: np.ndarray
    library: np.ndarray
    load_kn: np.ndarray
    stroke_m: np.ndarray
    source: np.ndarray

    def __len__(self) -> int:
        return len(self.poses)


def designable_robot(robot: Robot, approach_mm: float) -> Robot:
    """The robot with its lower leg limit raised by approach_mm + 1 mm: every candidate's approach point fits."""
    lo, hi = robot.leg_limits
    margin = LegLimitSpec(min_mm=lo + approach_mm + DESIGN_MARGIN_MM, max_mm=hi)
    return Robot(robot.spec.model_copy(update={"leg_limits": margin}))


def boundary_poses(robot: Robot, n: int, rng: np.random.Generator) -> np.ndarray:
    """n feasible poses (n, 6) on the boundary of the feasible region, along seeded random rays from home.

    Directions are uniform on the sphere of the workspace box scaled to [-1, 1]; each ray is cut at the box and
    then bisected between home (feasible) and the cut until feasibility ends, to within 2^-30 of the ray.
    """
    if n < 0:
        raise ValueError(f"n must be non-negative, got {n}")
    home = robot.home
    if not feasible(robot, home[None])[0]:
        raise ValueError("home is not feasible for this robot: no rays can start there")
    ws = robot.workspace
    direction = rng.normal(size=(n, 6))
    direction *= (ws[:, 1] - ws[:, 0]) / 2 / np.linalg.norm(direction, axis=1, keepdims=True)
    with np.errstate(divide="ignore", invalid="ignore"):
        to_box = np.where(direction > 0, (ws[:, 1] - home) / direction,
                          np.where(direction < 0, (ws[:, 0] - home) / direction, np.inf))
    lo, hi = np.zeros(n), to_box.min(axis=1)
    at_box = feasible(robot, home + hi[:, None] * direction)
    for _ in range(BISECTION_STEPS):
        mid = (lo + hi) / 2
        ok = feasible(robot, home + mid[:, None] * direction)
        lo, hi = np.where(ok, mid, lo), np.where(ok, hi, mid)
    reach = np.where(at_box, to_box.min(axis=1), lo)
    return home + reach[:, None] * direction


def library_variables(robot: Robot, poses: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Axial leg loads (kN, compression positive) from the moving mass, and strokes (m), [N, 6] each, nominal."""
    q = np.atleast_2d(np.asarray(poses, dtype=float))
    geom = Geometry.nominal(robot)
    load = leg_forces(geom, q, gravity_wrench(robot, q)) / 1000.0
    stroke = (inverse_kinematics(geom, q) - robot.l0) / 1000.0
    return load, stroke


def library_columns(jacobians: np.ndarray, load_kn: np.ndarray, stroke_m: np.ndarray) -> np.ndarray:
    """[N, 6, 12]: each leg's length column of the pose-error Jacobian times its load, then times its stroke."""
    leg_length = jacobians[..., 6::7]
    return np.concatenate([leg_length * load_kn[:, None, :], leg_length * stroke_m[:, None, :]], axis=-1)


def candidate_set(robot: Robot, seed: int, *, approach_mm: float = 2.0, n_boundary: int = 1000, n_random: int = 1000,
                  reference: np.ndarray | None = None) -> CandidateSet:
    """The seeded candidate set (see the module docstring); reference poses must be feasible for the margin too."""
    if min(n_boundary, n_random) < 0:
        raise ValueError(f"candidate counts must be non-negative, got {n_boundary} and {n_random}")
    designable = designable_robot(robot, approach_mm)
    ray_rng, random_rng = (np.random.default_rng(s) for s in np.random.SeedSequence([seed, 0xCA7D]).spawn(2))
    parts = [("factorial", factorial_candidates(designable, 3)), ("boundary", boundary_poses(designable, n_boundary,
                                                                                               ray_rng)),
             ("random", random_poses(designable, n_random, random_rng))]
    if reference is not None:
        ref = np.unique(np.atleast_2d(np.asarray(reference, dtype=float)), axis=0)
        bad = np.flatnonzero(~feasible(designable, ref))
        if bad.size:
            raise ValueError(f"reference poses {bad[:5].tolist()} leave the workspace or the leg limits "
                             f"(with the approach margin of {approach_mm + DESIGN_MARGIN_MM:g} mm)")
        parts.append(("reference", ref))
    poses = np.concatenate([p for _, p in parts])
    source = np.concatenate([np.full(len(p), name) for name, p in parts])
    jac = pose_jacobians(robot, poses)
    load, stroke = library_variables(robot, poses)
    return CandidateSet(poses, jac, library_columns(jac, load, stroke), load, stroke, source)
