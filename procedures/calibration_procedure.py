"""The calibration procedure as a plain generator of messages (see `procedures.messages`).

Measure the plan's measurement and verification poses on the uncalibrated controller, identify (LS and
L-infinity on the same rows), check plausibility, compensate (full geometry, or best leg offsets),
upload after confirmation, then re-measure the verification poses on the compensated controller.
Poses already in the journal are skipped, so a resumed run continues where it stopped.
"""

from __future__ import annotations

from collections.abc import Generator
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from drivers.controller_modbus import ParameterSet
from hilcal import design
from hilcal.calibration import CalibrationOutcome, calibrate
from hilcal.compensation import Compensation, ControllerGeometry, compensate, plausibility
from hilcal.kinematics import forward_kinematics, inverse_kinematics
from hilcal.recording import Recording, recording_from_arrays
from hilcal.robot import Robot
from procedures import messages as m
from procedures.plan import CalibrationPlan, waypoints

PRE_PHASES = ("measure", "verify")
AFTER_PHASE = "verify_after"


@dataclass(frozen=True)
class RunOptions:
    estimator: str = "ls"
    force: bool = False
    save: bool = True
    joint_bound_mm: float = 10.0
    offset_bound_mm: float = 20.0


@dataclass
class ProcedureResult:
    status: str
    recording: Recording | None = None
    outcomes: dict[str, CalibrationOutcome] = field(default_factory=dict)
    chosen: str = "ls"
    problems: list[str] = field(default_factory=list)
    compensation: Compensation | None = None
    before_params: ParameterSet | None = None
    upload: dict | None = None
    after_rows: list[dict] = field(default_factory=list)


def controller_geometry(params: ParameterSet) -> ControllerGeometry:
    return ControllerGeometry(np.array(params.a_mm), np.array(params.b_mm), np.array(params.l0_mm))


def to_parameter_set(geom: ControllerGeometry) -> ParameterSet:
    return ParameterSet(a_mm=geom.a.tolist(), b_mm=geom.b.tolist(), l0_mm=geom.l0.tolist())


def recording_from_rows(rows: list[dict], robot: Robot) -> Recording:
    """The journal's pre-calibration rows in the recording format (phase measure/verify, execution order)."""
    return recording_from_arrays(
        seq=[r["seq"] for r in rows], phase=[r["phase"] for r in rows], time_s=[r["time_s"] for r in rows],
        cmd=np.array([r["cmd"] for r in rows]), legs_mm=np.array([r["legs"] for r in rows]),
        meas=np.array([r["meas"] for r in rows]),
        extra={"sphere_fit_rms_mm": [r["detail"].get("sphere_fit_rms_mm", np.nan) for r in rows]},
        robot=robot, source="<run journal>",
    )


def visit(geom: ControllerGeometry, pose: np.ndarray, target: np.ndarray, plan: CalibrationPlan,
          label: str) -> Generator[Any, Any, np.ndarray]:
    """Move from `pose` to `target` in bounded steps, arriving with every leg extending; returns the target."""
    ik = geom.ik_geometry()
    for kind, waypoint in waypoints(ik, pose, target, plan):
        legs = inverse_kinematics(ik, waypoint)
        if kind == "approach":
            legs = legs - plan.approach_mm
        yield m.MoveLegs(m.as_tuple(legs), f"{label} {kind}")
    return target


def _measure_phase(phase: str, poses: np.ndarray, geom: ControllerGeometry, pose: np.ndarray,
                   plan: CalibrationPlan) -> Generator[Any, Any, np.ndarray]:
    done = {row["index"] for row in (yield m.Recall((phase,)))}
    for k, target in enumerate(poses):
        if k in done:
            continue
        pose = yield from visit(geom, pose, target, plan, f"{phase} {k + 1}")
        yield m.Settle(plan.settle_s)
        yield m.Measure(phase, k, m.as_tuple(target))
    return pose


def calibration_procedure(plan: CalibrationPlan, robot: Robot, options: RunOptions
                          ) -> Generator[Any, Any, ProcedureResult]:
    """Measure, identify, upload, verify. Returns what the report needs."""
    yield m.Prompt("spheres", "Mount the three platform and three base tooling spheres; CMM homed and aligned?")
    yield m.Prompt("area", "Clear the area around the platform: it is about to move. Go on?")
    yield m.PrepareCmm()
    before, info = yield m.ReadParams("before")
    geom = controller_geometry(before)
    pose = forward_kinematics(geom.ik_geometry(), (yield m.ReadLegs()), robot.home)[0]
    yield m.Enable()
    for phase in PRE_PHASES:
        pose = yield from _measure_phase(phase, plan.poses(phase), geom, pose, plan)
    rec = recording_from_rows((yield m.Recall(PRE_PHASES)), robot)
    result = ProcedureResult("measured", recording=rec, chosen=options.estimator, before_params=before)
    result.outcomes = {est: calibrate(rec, robot, estimator=est) for est in ("ls", "linf")}
    chosen = result.outcomes[options.estimator].identification
    result.problems = plausibility(chosen, options.joint_bound_mm, options.offset_bound_mm)
    if result.problems and not options.force:
        yield m.Disable()
        result.status = "refused"
        yield m.Checkpoint("refused", {"problems": result.problems})
        return result
    samples = design.verification_poses(robot, 64, plan.seed + 1)
    result.compensation = compensate(robot, geom, chosen, bool(info["offsets_only"]), samples)
    new_params = to_parameter_set(result.compensation.parameters)
    yield m.Checkpoint("identified", {"estimator": options.estimator, "mode": result.compensation.mode})
    yield m.Prompt("upload", f"Upload the {result.compensation.mode.replace('_', ' ')} parameter set "
                             f"({options.estimator}) to the controller?")
    yield m.Disable()
    result.upload = yield m.Upload(new_params, options.save)
    yield m.Enable()
    pose = yield from _measure_phase(AFTER_PHASE, plan.poses("verify"), result.compensation.parameters, pose, plan)
    yield m.Disable()
    result.after_rows = yield m.Recall((AFTER_PHASE,))
    result.status = "complete"
    yield m.Checkpoint("complete")
    return result
