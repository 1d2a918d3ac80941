"""The calibration procedure as a plain generator of messages (see `procedures.messages`).

Measure the plan's measurement poses (or, for an adaptive run, the poses ``hilcal.planning.sequential`` chooses one
at a time until the accuracy is proven: ``procedures.adaptive``) and verification poses on the uncalibrated
controller, identify (LS and
L-infinity on the same rows), diagnose the missing physics (``procedures.physics``), check plausibility, compensate
(full geometry, or best leg offsets, with the compensation block where the controller has one), upload after
confirmation, then re-measure the verification poses on the compensated controller and, if asked, run the ISO 9283
acceptance test (``procedures.acceptance``) on it. Poses already in the journal are skipped, so a resumed run
continues where it stopped.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Generator
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from drivers.controller.modbus import CompensationBlock, ParameterSet
from hilcal.calibration import CalibrationOutcome, calibrate, stated_pose_noise
from hilcal.compensation import Compensation, ControllerGeometry, compensate, held_out_after, out_of_reach
from hilcal.kinematics import forward_kinematics, inverse_kinematics
from hilcal.leg_compensation import LegCompensation
from hilcal.protocols.registers import Capability
from hilcal.recording import Recording, recording_from_arrays
from hilcal.robot import Robot
from procedures import messages as m
from procedures.acceptance import ACCEPTANCE_PHASE, AcceptanceTest
from procedures.acquisition import AFTER_UPLOAD_TIGHTENING, Acquisition
from procedures.adaptive import PROGRESS_LABEL, STOP_LABEL, AdaptiveRun, check_route_on, progress
from procedures.approval import approval_detail, workspace_samples
from procedures.physics import ControllerInfo, PhysicsDecision, decide
from procedures.plan import CalibrationPlan, return_waypoints, waypoints

CMM_SETUP = "Mount the three platform and three base tooling spheres; CMM homed and aligned?"
PRE_PHASES = ("measure", "verify")
AFTER_PHASE = "verify_after"
TIMED_PHASES = (*PRE_PHASES, AFTER_PHASE, ACCEPTANCE_PHASE, "return_home")
"""Phases whose start and end the procedure journals (checkpoints phase_start:NAME, phase_end:NAME)."""


@dataclass(frozen=True)
class RunOptions:
    estimator: str = "ls"
    force: bool = False
    save: bool = True
    joint_bound_mm: float = 10.0
    offset_bound_mm: float = 20.0
    acceptance: AcceptanceTest | None = None
    physics: bool = True
    """Diagnose the run's own recording and upload what it finds with the geometry (False: the geometry alone)."""
    adaptive: AdaptiveRun | None = None
    """Measure adaptively (the plan's measure poses are then only the reference and candidates); None: the plan."""
    setup_prompt: str = CMM_SETUP
    """What the operator confirms of the instrument's set-up before anything moves (the station's instrument's)."""
    pose_sigma: tuple[float, float] | None = None
    """The instrument's pose noise (mm, deg) as the diagnosis' yardstick (a laser tracker's MPE); None: its own."""


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
    out_of_reach: list[str] = field(default_factory=list)
    acquisition: list[str] = field(default_factory=list)
    """What the measurement met: gross set-up faults measured as they are, poses skipped as out of reach."""
    acceptance_rows: list[dict] = field(default_factory=list)
    physics: PhysicsDecision | None = None
    block: CompensationBlock | None = None
    """The compensation block uploaded with the geometry (None: the controller kept its own)."""
    adaptive: dict | None = None
    """An adaptive run's last decision (``procedures.adaptive.progress``: the stop, its prediction, the rows)."""


def controller_geometry(params: ParameterSet) -> ControllerGeometry:
    return ControllerGeometry(np.array(params.a_mm), np.array(params.b_mm), np.array(params.l0_mm))


def to_parameter_set(geom: ControllerGeometry) -> ParameterSet:
    return ParameterSet(a_mm=geom.a.tolist(), b_mm=geom.b.tolist(), l0_mm=geom.l0.tolist())


def to_block(comp: LegCompensation) -> CompensationBlock:
    """The controller's compensation block for these terms (validated as the controller would)."""
    return CompensationBlock.from_block(comp.to_json())


def controller_info(before: ParameterSet, info: dict) -> ControllerInfo:
    """What the journaled ReadParams says about the controller (runs journaled before register map 1.1 included)."""
    caps = Capability(int(info.get("capabilities", 0)))
    block = info.get("compensation")
    return ControllerInfo(np.asarray(before.l0_mm, dtype=float), offsets_only=bool(info["offsets_only"]),
                          compensation=Capability.COMPENSATION in caps,
                          force_reading=Capability.FORCE_READING in caps,
                          temperature_reading=Capability.TEMPERATURE_READING in caps,
                          live_block=LegCompensation() if block is None else LegCompensation.from_json(block))




def recording_from_rows(rows: list[dict], robot: Robot) -> Recording:
    """The journal's pre-calibration rows in the recording format (phase measure/verify, execution order); with the
    controller's leg temperature at every row when it reads one."""
    extra = {"sphere_fit_rms_mm": [r["detail"].get("sphere_fit_rms_mm", np.nan) for r in rows]}
    if rows and all("temp_c" in r["detail"] for r in rows):
        extra["temp_c"] = [r["detail"]["temp_c"] for r in rows]
    return recording_from_arrays(
        seq=[r["seq"] for r in rows], phase=[r["phase"] for r in rows], time_s=[r["time_s"] for r in rows],
        cmd=np.array([r["cmd"] for r in rows]), legs_mm=np.array([r["legs"] for r in rows]),
        meas=np.array([r["meas"] for r in rows]), extra=extra, robot=robot, source="<run journal>",
    )


def identification_summary(result: ProcedureResult, top: int = 12) -> dict[str, Any]:
    """Both estimators' fit and verification accuracy, and the chosen one's largest parameters (mm)."""
    estimators = {}
    for name, outcome in result.outcomes.items():
        ident = outcome.identification
        estimators[name] = {"converged": ident.converged, "max_residual_mm": ident.max_abs_residual,
                            "rms_residual_mm": ident.rms_residual, "model": ident.model,
                            "verify_before": outcome.before.brief() if outcome.before else None,
                            "verify_identified_model": outcome.after.brief() if outcome.after else None}
    chosen = result.outcomes[result.chosen].identification
    std = chosen.std_errors if chosen.std_errors is not None else [None] * len(chosen.names)
    order = np.argsort(-np.abs(chosen.x))[:top]
    largest = [{"name": chosen.names[i], "value_mm": float(chosen.x[i]),
                "std_mm": None if std[i] is None else float(std[i])} for i in order]
    return {"chosen": result.chosen, "estimators": estimators, "largest_parameters": largest,
            "n_parameters": len(chosen.names)}


def visit(geom: ControllerGeometry, pose: np.ndarray, target: np.ndarray, plan: CalibrationPlan,
          label: str) -> Generator[Any, Any, np.ndarray]:
    """Move from `pose` to `target` in bounded steps, arriving with every leg extending; returns the leg lengths the
    controller reached at the target."""
    ik = geom.ik_geometry()
    reached = inverse_kinematics(ik, target)
    for kind, waypoint in waypoints(ik, pose, target, plan):
        legs = inverse_kinematics(ik, waypoint)
        if kind == "approach":
            legs = legs - plan.approach_mm
        elif kind == "retreat":
            legs = legs - plan.repeat_retreat_mm
        reached = yield m.MoveLegs(m.as_tuple(legs), f"{label} {kind}")
    return np.asarray(reached, dtype=float)


def measure_here(acq: Acquisition, phase: str, index: int, cmd: np.ndarray, reached: np.ndarray
                 ) -> Generator[Any, Any, dict]:
    """Measure the pose the platform is at, predicted by the run's model from the reached legs; the model learns the
    row."""
    expected = acq.expect(reached, cmd)
    row = yield m.Measure(phase, index, m.as_tuple(cmd),
                          None if expected is None else m.as_tuple(expected.pose),
                          None if expected is None else m.as_tuple(expected.cov))
    acq.learn(row)
    return row


def return_home(geom: ControllerGeometry, pose: np.ndarray, robot: Robot, plan: CalibrationPlan
                ) -> Generator[Any, Any, np.ndarray]:
    """Back to the home pose in bounded steps (nothing is measured there, so no approach); phase return_home."""
    ik = geom.ik_geometry()
    yield m.Checkpoint("phase_start:return_home")
    for kind, waypoint in return_waypoints(ik, pose, robot.home, plan):
        yield m.MoveLegs(m.as_tuple(inverse_kinematics(ik, waypoint)), f"return home {kind}")
    yield m.Checkpoint("phase_end:return_home")
    return robot.home


def _measure_phase(phase: str, poses: np.ndarray, geom: ControllerGeometry, pose: np.ndarray,
                   plan: CalibrationPlan, acq: Acquisition, skip: frozenset[int] = frozenset(),
                   skipped: dict[int, str] | None = None) -> Generator[Any, Any, np.ndarray]:
    """Visit and measure the phase's poses not yet in the journal (nor in `skip`: out of the machine's reach); a
    pose the run's model says would drive a leg beyond its travel is skipped and said in `skipped` (index: why).
    Checkpoints time the phase (first start kept)."""
    done = {row["index"] for row in (yield m.Recall((phase,)))}
    todo = [k for k in range(len(poses)) if k not in done and k not in skip]
    if todo and not done:
        yield m.Checkpoint(f"phase_start:{phase}")
    ik = geom.ik_geometry()
    for k in todo:
        target = inverse_kinematics(ik, poses[k])
        why = acq.unreachable(np.vstack([target - plan.approach_mm, target]), f"{phase.replace('_', ' ')} pose {k + 1}")
        if why is not None:
            if skipped is not None:
                skipped[k] = why
            yield m.Checkpoint(f"skipped:{phase}:{k + 1}", {"reason": why})
            continue
        reached = yield from visit(geom, pose, poses[k], plan, f"{phase} {k + 1}")
        pose = poses[k]
        yield m.Settle(plan.settle_s)
        yield from measure_here(acq, phase, k, poses[k], reached)
    if todo:
        yield m.Checkpoint(f"phase_end:{phase}")
    return pose


def _adaptive_measure_phase(run: AdaptiveRun, geom: ControllerGeometry, pose: np.ndarray, plan: CalibrationPlan,
                            acq: Acquisition) -> Generator[Any, Any, tuple[np.ndarray, dict]]:
    """Ask for the next pose, visit and measure it, update; until the stop. The journaled rows are replayed first,
    so a resumed run is in the same state and makes the same next choices. Returns the pose and the last decision."""
    from hilcal.planning.sequential import decide, replay, update

    problem = run.problem
    rows = yield m.Recall(("measure",))
    state = replay(problem, [(r["cmd"], r["legs"], r["meas"]) for r in rows])
    if not rows:
        yield m.Checkpoint("phase_start:measure")
    measured = False
    while True:
        decision = decide(problem, state, run.memo)
        shown = progress(run, state, decision)
        yield m.Checkpoint(PROGRESS_LABEL, shown)
        if decision.stop is not None:
            break
        k = state.n_rows
        reached = yield from visit(geom, pose, decision.next.pose, plan, f"measure {k + 1}")
        pose = decision.next.pose
        yield m.Settle(plan.settle_s)
        row = yield from measure_here(acq, "measure", k, decision.next.pose, reached)
        state = update(problem, state, row["cmd"], row["legs"], row["meas"])
        measured = True
    if measured:
        yield m.Checkpoint("phase_end:measure")
    yield m.Checkpoint(STOP_LABEL, shown)
    check_route_on(plan, state.commanded(), problem.robot)
    return pose, shown


def calibration_procedure(plan: CalibrationPlan, robot: Robot, options: RunOptions
                          ) -> Generator[Any, Any, ProcedureResult]:
    """Measure, identify, upload, verify. Returns what the report needs."""
    yield m.Prompt("spheres", options.setup_prompt)
    yield m.Prompt("area", "Clear the area around the platform: it is about to move. Go on?")
    yield m.PrepareCmm()
    before, info = yield m.ReadParams("before")
    geom = controller_geometry(before)
    acq = Acquisition.start(robot, geom.a, geom.b, geom.l0, (yield m.Recall(PRE_PHASES)))
    legs_now = yield m.ReadLegs()
    acq.check_readings(legs_now)
    pose = forward_kinematics(geom.ik_geometry(), legs_now, robot.home)[0]
    yield m.Enable()
    adaptive = None
    skipped: dict[int, str] = {}
    skipped_verify: dict[int, str] = {}
    if options.adaptive is not None:
        pose, adaptive = yield from _adaptive_measure_phase(options.adaptive, geom, pose, plan, acq)
    else:
        pose = yield from _measure_phase("measure", plan.poses("measure"), geom, pose, plan, acq, skipped=skipped)
    pose = yield from _measure_phase("verify", plan.poses("verify"), geom, pose, plan, acq, skipped=skipped_verify)
    noted = [*acq.notes, *skipped.values(), *skipped_verify.values()]
    rows = yield m.Recall(PRE_PHASES)
    if adaptive is not None and adaptive["stop"]["kind"] == "not_identifiable":
        yield from return_home(geom, pose, robot, plan)
        yield m.Disable()
        result = ProcedureResult("not identifiable", chosen=options.estimator, before_params=before,
                                 adaptive=adaptive, acquisition=noted)
        result.problems = [adaptive["stop"]["sentence"]]
        yield m.Checkpoint("not_identifiable", {"problems": result.problems})
        return result
    rec = recording_from_rows(rows, robot)
    result = ProcedureResult("measured", recording=rec, chosen=options.estimator, before_params=before,
                             adaptive=adaptive, acquisition=noted)
    stated = {} if options.pose_sigma is None else {  # the instrument states its pose noise (a tracker's MPE)
        "noise_covariance": stated_pose_noise(int(np.sum(rec.phase == "measure")), robot, options.pose_sigma)}
    result.outcomes = {est: calibrate(rec, robot, estimator=est, **(stated if est == "ls" else {}))
                       for est in ("ls", "linf")}
    controller = controller_info(before, info)
    physics = decide(rec, robot, result.outcomes[options.estimator], controller, physics=options.physics,
                     joint_bound_mm=options.joint_bound_mm, offset_bound_mm=options.offset_bound_mm,
                     pose_sigma=options.pose_sigma)
    result.physics = physics
    result.problems = physics.problems
    if result.problems and not options.force:
        yield m.Disable()
        result.status = "refused"
        yield m.Checkpoint("refused", {"problems": result.problems, "findings": physics.findings,
                                       "identification": identification_summary(result)})
        return result
    samples = workspace_samples(robot, plan.seed + 1)
    result.compensation = compensate(robot, geom, physics.geometry_x, controller.offsets_only, samples)
    verify = rec.phase == "verify"
    if result.compensation.mode == "offsets_only" and physics.block is None and verify.any():
        # the held-out prediction of the geometry's fit assumes the controller takes the joints too: this one keeps
        # its a and b, so the verification after the upload measures what the offsets alone leave
        physics.predicted_with = held_out_after(robot, geom, physics.geometry_x, result.compensation.parameters,
                                                rec.legs_mm[verify], rec.meas[verify], rec.cmd[verify])
    if physics.block is not None:
        params = result.compensation.parameters
        shifted = ControllerGeometry(params.a, params.b, params.l0 + physics.l0_shift_mm)
        result.compensation = dataclasses.replace(result.compensation, parameters=shifted)
        result.block = to_block(physics.block)
    new_params = to_parameter_set(result.compensation.parameters)
    reach = out_of_reach(robot, result.compensation.parameters, physics.block, plan.poses("verify"), plan.approach_mm)
    result.out_of_reach = [r.sentence("verify pose") + ": it is not measured after the upload" for r in reach]
    what = result.compensation.mode.replace("_", " ") + (" and compensation block" if result.block else "")
    yield m.Checkpoint("identified", {"estimator": options.estimator, "mode": result.compensation.mode,
                                      "problems": result.problems, "physics": physics.to_json(),
                                      "out_of_reach": result.out_of_reach,
                                      "identification": identification_summary(result)})
    detail = approval_detail(before, new_params, result.block, result.compensation, result.outcomes[result.chosen],
                             result.chosen, physics, robot, samples)
    yield m.Prompt("upload", f"Upload the {what} ({options.estimator}) to the controller?",
                   {**detail, "out_of_reach": result.out_of_reach})
    yield m.Disable()
    result.upload = yield m.Upload(new_params, options.save, result.block)
    yield m.Enable()
    uploaded = result.compensation.parameters
    after = Acquisition.start(robot, uploaded.a, uploaded.b, uploaded.l0,
                              (yield m.Recall((AFTER_PHASE, ACCEPTANCE_PHASE))), tightening=AFTER_UPLOAD_TIGHTENING)
    pose = yield from _measure_phase(AFTER_PHASE, plan.poses("verify"), uploaded, pose, plan, after,
                                     skip=frozenset(r.index for r in reach) | frozenset(skipped_verify))
    if options.acceptance is not None:
        route, _ = options.acceptance.route()
        pose = yield from _measure_phase(ACCEPTANCE_PHASE, route, uploaded, pose, plan, after)
    pose = yield from return_home(result.compensation.parameters, pose, robot, plan)
    yield m.Disable()
    result.after_rows = yield m.Recall((AFTER_PHASE,))
    if options.acceptance is not None:
        result.acceptance_rows = yield m.Recall((ACCEPTANCE_PHASE,))
    result.status = "complete"
    yield m.Checkpoint("complete")
    return result
