"""Calibration plans: the measurement and verification poses and the motion rules, stored with a hash.

A plan is a JSON file; the same plan can be re-run later to check a machine. Every target is checked
against the workspace and the leg limits (with the approach offset and a repeat's retreat) when the plan
is made or loaded, before any motion. New plans visit their poses in the order of least machine time
(``hilcal.planning.ordering``) and measure one pose four times in a row (a noise yardstick for the diagnosis).
"""

from __future__ import annotations

import hashlib
import json
from pathlib import Path
from typing import Annotated, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator

from hilcal.kinematics import Geometry, inverse_kinematics
from hilcal.planning import design
from hilcal.planning.machine_time import (
    MotionRules,
    MotionTiming,
    TimeEstimate,
    calibration_phases,
    estimate_route,
    interpolated_poses,
    move_costs,
    repeatable_pose,
)
from hilcal.planning.ordering import RouteOrder, order_route
from hilcal.robot import POSE_AXES, LegLimitSpec, Robot

REPEATS = 3
"""Extra measurements of the repeated pose in the default plan (measured 4 times in a row)."""

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
    repeat_retreat_mm: float = Field(default=10.0, gt=0.0, le=100.0,
                                     description="a repeat of the same pose first retracts every leg this much")
    order: Literal["design", "time", "adaptive"] = Field(default="design", description="design order, least machine "
                                                         "time, or as an adaptive run chose and measured them")
    seed: int = 0

    @model_validator(mode="after")
    def _retreat_leaves_the_pose(self) -> CalibrationPlan:
        if self.repeat_retreat_mm < 3 * self.approach_mm:
            raise ValueError(f"repeat_retreat_mm ({self.repeat_retreat_mm}) must be at least 3 × approach_mm "
                             f"({self.approach_mm}): a repeat must leave the pose, not only re-approach it")
        return self

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
        repeat = np.concatenate([[False], np.all(poses[1:] == poses[:-1], axis=1)])
        for k, row in enumerate(legs):
            low = plan.repeat_retreat_mm if repeat[k] else plan.approach_mm
            if row.min() - low < lo or row.max() > hi:
                what = f"repeat retreat {plan.repeat_retreat_mm}" if repeat[k] else f"approach {plan.approach_mm}"
                raise PlanError(f"{phase} pose {k + 1}: leg lengths {np.round(row, 1).tolist()} mm ({what} mm) "
                                f"leave the leg limits [{lo}, {hi}] mm")
    _check_route(plan, robot)


_LIMITS_ONLY = MotionTiming(1.0, 1.0, 0.0, 0.0)
"""Any timing: the route check only looks at the leg setpoints."""


def _check_route(plan: CalibrationPlan, robot: Robot) -> None:
    """Every setpoint of the route from home through the phases and back stays within the leg limits.

    Legs are not linear in the pose: the straight line between two reachable poses can leave the limits.
    """
    labels = ["home", *[f"measure pose {k + 1}" for k in range(len(plan.measure_poses))],
              *[f"verify pose {k + 1}" for k in range(len(plan.verify_poses))] * 2]
    route = np.vstack([robot.home, plan.poses("measure"), plan.poses("verify").reshape(-1, 6),
                       plan.poses("verify").reshape(-1, 6)])
    nominal = Geometry.nominal(robot)
    ok = move_costs(nominal, route[:-1], route[1:], motion_rules(plan), _LIMITS_ONLY).within(robot.leg_limits)
    back = move_costs(nominal, route[-1], robot.home, motion_rules(plan), _LIMITS_ONLY, approach=False)
    for k in np.flatnonzero(~ok):
        raise PlanError(f"the move from {labels[k]} to {labels[k + 1]} passes leg lengths outside the leg limits "
                        f"{list(robot.leg_limits)} mm (legs are not linear in the pose); reorder or change the poses")
    if not back.within(robot.leg_limits)[0]:
        raise PlanError(f"the move from {labels[-1]} back home leaves the leg limits {list(robot.leg_limits)} mm")


def distinct_measure_poses(plan: CalibrationPlan) -> tuple[np.ndarray, np.ndarray]:
    """The plan's measure poses with repeats collapsed (in visit order) and how often each is measured in a row."""
    rows = plan.poses("measure")
    keep = np.concatenate([[True], np.any(rows[1:] != rows[:-1], axis=1)])
    return rows[keep], np.diff(np.append(np.flatnonzero(keep), len(rows)))


def motion_rules(plan: CalibrationPlan) -> MotionRules:
    """The plan's motion rules for the machine-time model."""
    return MotionRules(plan.max_step_mm, plan.approach_mm, plan.repeat_retreat_mm)


def make_plan(robot: Robot, seed: int = 0, n_measure: int = 32, n_verify: int = 24, approach_mm: float = 2.0,
              settle_s: float | None = None, *, timing: MotionTiming, order: Literal["design", "time"] = "time",
              repeats: int = REPEATS) -> CalibrationPlan:
    """D-optimal measurement poses (factorial + coordinate exchange) and evenly spread verification poses.

    The poses are designed with the lower leg limit raised by the approach distance (plus 1 mm), so the
    approach point of every pose is reachable too. settle_s None: the timing's settle wait.
    """
    lo, hi = robot.leg_limits
    margin = LegLimitSpec(min_mm=lo + approach_mm + 1.0, max_mm=hi)
    designable = Robot(robot.spec.model_copy(update={"leg_limits": margin}))
    measure = design.factorial_exchange(designable, n_measure, np.random.default_rng(seed)).poses
    verify = design.verification_poses(designable, n_verify, seed)
    return plan_from_poses(robot, measure, verify, timing=timing, seed=seed, approach_mm=approach_mm,
                           settle_s=timing.settle_s if settle_s is None else settle_s, order=order, repeats=repeats)


def plan_from_poses(robot: Robot, measure: np.ndarray, verify: np.ndarray, *, timing: MotionTiming, seed: int = 0,
                    approach_mm: float = 2.0, settle_s: float = 0.5, order: Literal["design", "time"] = "time",
                    repeats: int = REPEATS) -> CalibrationPlan:
    """A checked plan of these poses: one measured 1 + `repeats` times in a row, in design or least-time order.

    The repeated pose is the one with the most room below it for the retreat (``repeatable_pose``).
    """
    # rounded to 1 nm for the plan file, and kept inside the workspace: a bound at the edge of a robot file's
    # workspace (a home height from leg lengths has more decimals) must not round to just outside it
    M, V = (np.clip(np.round(np.atleast_2d(p), 6).reshape(-1, 6), robot.workspace[:, 0], robot.workspace[:, 1])
            for p in (measure, verify))
    base = CalibrationPlan(robot_name=robot.name, measure_poses=M.tolist(), verify_poses=V.tolist(), seed=seed,
                           approach_mm=approach_mm, settle_s=settle_s, order=order)
    counts = np.ones(len(M), dtype=int)
    if repeats:
        geom = Geometry.nominal(robot)
        try:
            counts[repeatable_pose(geom, M, robot.leg_limits[0], motion_rules(base))] += repeats
        except ValueError as e:
            raise PlanError(str(e)) from None
    m_order, v_order = np.arange(len(M)), np.arange(len(V))
    if order == "time":
        route = order_plan_route(robot, M, V, base, timing, counts)
        m_order, v_order = route.measure_order, route.verify_order
    rows = np.repeat(M[m_order], counts[m_order], axis=0)
    plan = base.model_copy(update={"measure_poses": rows.tolist(), "verify_poses": V[v_order].tolist()})
    check_plan(plan, robot)
    return plan


def order_plan_route(robot: Robot, measure: np.ndarray, verify: np.ndarray, plan: CalibrationPlan,
                     timing: MotionTiming, counts: np.ndarray) -> RouteOrder:
    """The least-time order of distinct measure poses (measured counts[k] times) and verify poses, seeded."""
    return order_route(Geometry.nominal(robot), robot.home, measure, verify, motion_rules(plan),
                       timing_for(plan, timing), measure_counts=counts, seed=plan.seed, leg_limits=robot.leg_limits)


def timing_for(plan: CalibrationPlan, timing: MotionTiming) -> MotionTiming:
    """The station's timing with the plan's own settle wait (what the procedure really waits)."""
    return MotionTiming(timing.leg_speed_mm_s, timing.leg_accel_mm_s2, plan.settle_s, timing.cmm_s_per_pose,
                        timing.move_overhead_s)


def estimate_plan(plan: CalibrationPlan, robot: Robot, timing: MotionTiming, start_pose: np.ndarray | None = None,
                  acceptance_poses: np.ndarray | None = None) -> TimeEstimate:
    """Estimated machine time of running the plan from start_pose (default home) and back home, per phase; with
    the acceptance test's poses in visiting order, its phase too."""
    start = robot.home if start_pose is None else np.asarray(start_pose, dtype=float)
    return estimate_route(Geometry.nominal(robot), start, calibration_phases(plan.poses("measure"),
                                                                             plan.poses("verify"), acceptance_poses),
                          motion_rules(plan), timing_for(plan, timing), robot.home)


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

    Poses are interpolated in pose space (``hilcal.planning.machine_time.interpolated_poses``). The last two moves
    are the approach point (every leg approach_mm shorter than at the target) and the target itself, so each
    pose is reached with every leg extending: joint backlash is the same at every pose. A repeat (start
    equal to target) first retreats (every leg repeat_retreat_mm shorter), so it leaves the pose and
    re-seats the joints like any other visit.
    """
    start, target = np.asarray(start_pose, dtype=float), np.asarray(target_pose, dtype=float)
    if np.array_equal(start, target):
        return [("retreat", target), ("approach", target), ("target", target)]
    poses = interpolated_poses(geom, start, target, plan.max_step_mm)
    return [*[("transit", p) for p in poses[:-1]], ("approach", target), ("target", target)]


def return_waypoints(geom: Geometry, start_pose: np.ndarray, target_pose: np.ndarray, plan: CalibrationPlan
                     ) -> list[tuple[str, np.ndarray]]:
    """Bounded steps to a pose where nothing is measured (home at the end): no approach point."""
    poses = interpolated_poses(geom, np.asarray(start_pose, dtype=float), np.asarray(target_pose, dtype=float),
                               plan.max_step_mm)
    return [*[("transit", p) for p in poses[:-1]], ("target", poses[-1])]
