"""The ISO 9283 acceptance test of a run: the test poses P1-P5, the cycles and the route, checked before any motion.

The test is made from the robot file (``hilcal.acceptance``: the largest cube in the workspace, P1-P5 on its
diagonal plane) and stored with its hash in the run folder (``acceptance.json``) and in the journal, so a resumed
run measures exactly the same poses. It runs after the verification on the compensated controller: the cycles visit
P1, P5, P4, P3, P2 under the plan's motion rules (bounded steps, every pose approached from the same side).
"""

from __future__ import annotations

import hashlib
import json
from pathlib import Path
from typing import Annotated, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from hilcal.acceptance.iso9283 import CYCLE_ORDER, POSE_NAMES, cycle_route, iso_poses, largest_cube
from hilcal.kinematics import Geometry
from hilcal.planning.machine_time import MotionTiming, move_costs
from hilcal.robot import Robot
from procedures.plan import CalibrationPlan, PlanError, motion_rules

ACCEPTANCE_PHASE = "acceptance"
"""The journal phase of the acceptance test's measurements (on the compensated controller)."""
STANDARDS = ("iso9283",)

Pose = Annotated[list[float], Field(min_length=6, max_length=6)]
Vec3 = Annotated[list[float], Field(min_length=3, max_length=3)]


class AcceptanceTest(BaseModel):
    """The test poses (mm, deg), the number of cycles and the cube they come from."""

    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)

    standard: Literal["iso9283"] = "iso9283"
    robot_name: str
    cycles: int = Field(ge=2, le=1000, description="visits of every test pose (ISO 9283: 30)")
    cube_centre_mm: Vec3
    cube_side_mm: float = Field(gt=0)
    orientation_deg: Vec3
    poses: Annotated[list[Pose], Field(min_length=5, max_length=5)]
    """P1-P5 in that order."""

    def sha256(self) -> str:
        canonical = json.dumps(self.model_dump(), sort_keys=True, separators=(",", ":"))
        return hashlib.sha256(canonical.encode()).hexdigest()

    def route(self) -> tuple[np.ndarray, np.ndarray]:
        """Poses in visiting order (cycles * 5, 6) and the test pose of each (0 = P1)."""
        return cycle_route(np.array(self.poses, dtype=float), self.cycles)

    def describe(self) -> str:
        order = ", ".join(POSE_NAMES[k] for k in CYCLE_ORDER)
        return (f"ISO 9283 pose accuracy and repeatability: {self.cycles} cycles of {order}; test cube of side "
                f"{self.cube_side_mm:.1f} mm centred at {np.round(self.cube_centre_mm, 1).tolist()} mm")


def make_acceptance(robot: Robot, plan: CalibrationPlan, cycles: int, standard: str = "iso9283") -> AcceptanceTest:
    """The test for this robot, with the plan's approach margin on the lower leg limit; PlanError if none fits."""
    if standard not in STANDARDS:
        raise PlanError(f"unknown acceptance test {standard!r}: {', '.join(STANDARDS)}")
    if not 2 <= cycles <= 1000:
        raise PlanError(f"--cycles must be between 2 and 1000 (ISO 9283 uses 30), got {cycles}")
    try:
        cube = largest_cube(robot, lower_margin_mm=plan.approach_mm + 1.0)
    except ValueError as e:
        raise PlanError(str(e)) from None
    test = AcceptanceTest(robot_name=robot.name, cycles=cycles, cube_centre_mm=cube.centre_mm.tolist(),
                          cube_side_mm=cube.side_mm, orientation_deg=cube.orientation_deg.tolist(),
                          poses=np.round(iso_poses(cube), 6).tolist())
    check_acceptance(test, robot, plan)
    return test


_LIMITS_ONLY = MotionTiming(1.0, 1.0, 0.0, 0.0)


def check_acceptance(test: AcceptanceTest, robot: Robot, plan: CalibrationPlan) -> None:
    """Every setpoint of the test's route (from the last verification pose, through two cycles, back home) stays
    within the leg limits, approach points included; PlanError naming the move otherwise."""
    if test.robot_name != robot.name:
        raise PlanError(f"the acceptance test is for robot {test.robot_name!r}, not {robot.name!r}")
    rows, which = cycle_route(np.array(test.poses, dtype=float), min(test.cycles, 2))
    start = plan.poses("verify")[-1] if plan.verify_poses else plan.poses("measure")[-1]
    route = np.vstack([start, rows])
    labels = ["the last verification pose", *[POSE_NAMES[k] for k in which]]
    nominal = Geometry.nominal(robot)
    ok = move_costs(nominal, route[:-1], route[1:], motion_rules(plan), _LIMITS_ONLY).within(robot.leg_limits)
    for k in np.flatnonzero(~ok):
        raise PlanError(f"acceptance test: the move from {labels[k]} to {labels[k + 1]} leaves the leg limits "
                        f"{list(robot.leg_limits)} mm")
    back = move_costs(nominal, route[-1], robot.home, motion_rules(plan), _LIMITS_ONLY, approach=False)
    if not back.within(robot.leg_limits)[0]:
        raise PlanError(f"acceptance test: the move from {labels[-1]} back home leaves the leg limits")


def save_acceptance(test: AcceptanceTest, path: Path) -> None:
    path.write_text(json.dumps(test.model_dump(), indent=1) + "\n")
