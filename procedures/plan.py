"""Calibration plans: the measurement and verification poses and the motion rules, stored with a hash.

A plan is a JSON file; the same plan can be re-run later to check a machine. Every target is checked
against the workspace and the leg limits (with the approach offset) when the plan is made or loaded,
before any motion.
"""

from __future__ import annotations

import hashlib
import json
from pathlib import Path
from typing import Annotated

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, ValidationError

from hilcal import design
from hilcal.kinematics import Geometry, inverse_kinematics
from hilcal.robot import POSE_AXES, LegLimitSpec, Robot

Pose = Annotated[list[float], Field(min_length=6, max_length=6)]


class PlanError(ValueError):
    """A plan that cannot be read or that the robot cannot execute safely."""


class CalibrationPlan(BaseModel):
    """Poses in mm/deg ([x, y, z, roll, pitch, yaw]) and the rules for moving between them."""

    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)

    name: str = "calibration"
    robot_name: str
    measure_poses: Annotated[list[Pose], Field(min_length=8)]
    verify_poses: list[Pose]
    approach_mm: float = Field(default=2.0, ge=0.0, le=50.0,
                               description="every leg arrives extending by this much (same approach direction)")
    max_step_mm: float = Field(default=50.0, gt=0.0, description="largest leg-length change of one move")
    settle_s: float = Field(default=0.5, ge=0.0, description="wait after a move before measuring")
    seed: int = 0

    def sha256(self) -> str:
        """Hash of the canonical JSON: identifies the plan in journals, reports and records."""
        canonical = json.dumps(self.model_dump(), sort_keys=True, separators=(",", ":"))
        return hashlib.sha256(canonical.encode()).hexdigest()

    def poses(self, phase: str) -> np.ndarray:
        return np.array(self.measure_poses if phase == "measure" else self.verify_poses, dtype=float)


def check_plan(plan: CalibrationPlan, robot: Robot) -> None:
    """Refuse a plan whose targets or approach points leave the workspace or the leg limits."""
    if plan.robot_name != robot.name:
        raise PlanError(f"plan is for robot {plan.robot_name!r}, not {robot.name!r}")
    bounds = robot.workspace
    lo, hi = robot.leg_limits
    nominal = Geometry.nominal(robot)
    for phase in ("measure", "verify"):
        poses = plan.poses(phase)
        if poses.size == 0:
            continue
        for k, pose in enumerate(poses):
            outside = [POSE_AXES[j] for j in range(6) if not bounds[j, 0] <= pose[j] <= bounds[j, 1]]
            if outside:
                raise PlanError(f"{phase} pose {k + 1} is outside the workspace in {', '.join(outside)}")
        legs = inverse_kinematics(nominal, poses)
        for k, row in enumerate(legs):
            if row.min() - plan.approach_mm < lo or row.max() > hi:
                raise PlanError(f"{phase} pose {k + 1}: leg lengths {np.round(row, 1).tolist()} mm (approach "
                                f"{plan.approach_mm} mm) leave the leg limits [{lo}, {hi}] mm")


def make_plan(robot: Robot, seed: int = 0, n_measure: int = 32, n_verify: int = 24, approach_mm: float = 2.0,
              settle_s: float = 0.5) -> CalibrationPlan:
    """D-optimal measurement poses (factorial + coordinate exchange) and evenly spread verification poses.

    The poses are designed with the lower leg limit raised by the approach distance (plus 1 mm), so the
    approach point of every pose is reachable too.
    """
    lo, hi = robot.leg_limits
    margin = LegLimitSpec(min_mm=lo + approach_mm + 1.0, max_mm=hi)
    designable = Robot(robot.spec.model_copy(update={"leg_limits": margin}))
    measure = design.factorial_exchange(designable, n_measure, np.random.default_rng(seed)).poses
    verify = design.verification_poses(designable, n_verify, seed)
    plan = CalibrationPlan(robot_name=robot.name, measure_poses=np.round(measure, 6).tolist(),
                           verify_poses=np.round(verify, 6).tolist(), seed=seed, approach_mm=approach_mm,
                           settle_s=settle_s)
    check_plan(plan, robot)
    return plan


def save_plan(plan: CalibrationPlan, path: Path) -> None:
    path.write_text(json.dumps(plan.model_dump(), indent=1) + "\n")


def load_plan(path: Path, robot: Robot) -> CalibrationPlan:
    """Read and validate a plan file; PlanError with the reason if it is unusable."""
    try:
        plan = CalibrationPlan.model_validate_json(path.read_text())
    except OSError as e:
        raise PlanError(f"plan {path}: cannot read: {e.strerror}") from None
    except ValidationError as e:
        raise PlanError(f"plan {path}: {e.error_count()} problem(s): " + "; ".join(
            f"{'.'.join(map(str, err['loc']))}: {err['msg']}" for err in e.errors())) from None
    check_plan(plan, robot)
    return plan


def waypoints(geom: Geometry, start_pose: np.ndarray, target_pose: np.ndarray, plan: CalibrationPlan
              ) -> list[tuple[str, np.ndarray]]:
    """Intermediate poses so that no leg moves more than max_step_mm at once, then an approach point.

    Poses are interpolated in pose space (the workspace box is convex); legs are not linear in the pose,
    so the number of steps grows until every leg step is within the bound. The last two moves are the
    approach point (every leg approach_mm shorter than at the target) and the target itself, so each pose
    is reached with every leg extending: joint backlash is the same at every pose.
    """
    start_legs = inverse_kinematics(geom, start_pose)
    n = max(1, int(np.ceil(np.max(np.abs(inverse_kinematics(geom, target_pose) - start_legs)) / plan.max_step_mm)))
    while True:
        poses = start_pose + (target_pose - start_pose) * (np.arange(1, n + 1)[:, None] / n)
        legs = inverse_kinematics(geom, np.vstack([start_pose, poses]))
        if np.max(np.abs(np.diff(legs, axis=0))) <= plan.max_step_mm:
            break
        n += 1
    return [*[("transit", p) for p in poses[:-1]], ("approach", target_pose), ("target", target_pose)]
