"""`hilcal run`: the shop-floor runner. Opens the station's devices, runs the calibration procedure under
the engine with a journal, and writes the recording, the report and the calibration records.

The runner knows no simulator: for a ``--sim`` run the caller (the command line) passes ``RunRequest.sim_station``,
a context manager that starts the simulated devices and yields the station wired to them.

Exit codes: 0 complete, 2 bad input, 3 device fault, abort or refusal (journal kept, resumable), 4 complete but
not accepted (the sign-off verdict is fail or not proven; the certificate says which limit). A records database
that does not answer at the start is a refusal (3, nothing started); one lost mid-run only delays the records
(they wait in the run's journal for ``hilcal records sync``).
"""

from __future__ import annotations

import contextlib
import dataclasses
import datetime as dt
import json
import logging
import shlex
import shutil
import uuid
from collections.abc import Callable
from contextlib import AbstractContextManager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import structlog

from drivers.tracker.station import stations_summary
from hilcal.metrics import AccuracySummary, pose_errors
from hilcal.planning.machine_time import TimeEstimate
from hilcal.recording import write_recording
from hilcal.reports.timing import time_section
from hilcal.robot import Robot, RobotFileError, load_robot
from procedures.acceptance import ACCEPTANCE_PHASE, AcceptanceTest, make_acceptance, save_acceptance
from procedures.adaptive import (
    AdaptiveOptions,
    AdaptiveRun,
    adaptive_run,
    adaptive_summary,
    apply_start_plan,
    start_form,
    time_range_json,
    write_executed_plan,
)
from procedures.calibration_procedure import (
    AFTER_PHASE,
    PRE_PHASES,
    TIMED_PHASES,
    ProcedureResult,
    RunOptions,
    calibration_procedure,
    to_parameter_set,
)
from procedures.certificate import SignoffContext, finish_certificate, record_signoff, signoff_section, signoff_settings
from procedures.engine import Engine, RunInterrupted
from procedures.journal import Journal
from procedures.link_guard import links_summary
from procedures.plan import CalibrationPlan, PlanError, estimate_plan, load_plan, make_plan, save_plan
from procedures.records.run_records import record_outcome, record_start, records_target, stage_parameters
from procedures.run_progress import adaptive_lines, bar_aside, combine_observers, terminal_progress
from procedures.sections.tracker import instrument_options
from procedures.timing import TimingSection

EXIT_OK, EXIT_BAD_INPUT, EXIT_INTERRUPTED, EXIT_NOT_ACCEPTED = 0, 2, 3, 4


class SimulatorStartError(RuntimeError):
    """The simulated devices of a ``--sim`` run did not start (raised by a ``SimStation``)."""


SimStation = Callable[[str | None, Path, str | None, str | None], AbstractContextManager[Any]]
"""(sim_config, out_dir, robot_path, instrument) -> context manager that runs the simulated devices (the instrument:
"cmm", "tracker", or None for the simulator configuration's) and yields a ``SimulatedStation`` (or a bare station)."""


@dataclass(frozen=True)
class SimulatedStation:
    """The station wired to the simulated devices and what they simulate (``sim_devices.sim_config``'s summary: the
    robot, its errors, the effects, the instrument, the clock; its ``lines`` in words)."""

    station: Any
    simulation: dict | None = None


@dataclass(frozen=True)
class RunExit:
    code: int
    run_id: str
    message: str
    report_path: Path | None = None
    certificate_path: Path | None = None
    started: bool = True
    """False: the run never started (bad input, a device that did not answer): nothing of it is kept."""


def new_run_id() -> str:
    return dt.datetime.now(dt.UTC).strftime("%Y%m%dT%H%M%SZ-") + uuid.uuid4().hex[:6]


def configure_logs(out_dir: Path) -> None:
    """Structured JSON logs into the run folder; only warnings reach the console."""
    log_file = (out_dir / "run.log").open("a")
    structlog.configure(
        processors=[structlog.processors.add_log_level, structlog.processors.TimeStamper(fmt="iso"),
                    structlog.processors.JSONRenderer()],
        wrapper_class=structlog.make_filtering_bound_logger(logging.INFO),
        logger_factory=structlog.WriteLoggerFactory(log_file),
    )


def _per_pose(rows: list[dict], n_poses: int | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Position and orientation error per row; with n_poses, per pose index (NaN where a pose was not measured)."""
    meas = np.array([r["meas"] for r in rows])
    cmd = np.array([r["cmd"] for r in rows])
    position, orientation = pose_errors(meas, cmd)
    if n_poses is None:
        return position, orientation
    index = np.array([r["index"] for r in rows], dtype=int)
    aligned = np.full((2, n_poses), np.nan)
    aligned[0, index], aligned[1, index] = position, orientation
    return aligned[0], aligned[1]


def _summary(rows: list[dict]) -> AccuracySummary:
    return AccuracySummary.of(np.array([r["meas"] for r in rows]), np.array([r["cmd"] for r in rows]))


def run_with_devices(devices: Any, journal: Journal, plan: CalibrationPlan, robot: Robot, options: RunOptions,
                     out_dir: Path, run_id: str, confirm: Callable[[str], bool] | None,
                     started_at: str, timing: TimingSection | None = None,
                     observer: Callable[[str, dict], None] | None = None, recorder: Any = None,
                     signoff: Any = None, on_prompt: Callable[[Any], None] | None = None,
                     simulation: dict | None = None) -> RunExit:
    """Run (or continue) the procedure on open devices and write every output; never raises on device faults.

    `timing` (the station's) gives the report its estimated against actual machine time; `observer` receives
    the engine's events (the operator panel); `recorder` (``procedures.records.sync.RunRecorder``) gives the
    report the drift since the machine's earlier calibrations, and the journal stages the run's geometry;
    `signoff` (``procedures.certificate.SignoffContext``) makes a complete run's certificate and verdict;
    `simulation` (a --sim run's) says in the report what the simulator simulated.
    """
    done = len(journal.measurements((*PRE_PHASES, AFTER_PHASE, ACCEPTANCE_PHASE)))
    if done:
        journal.event("resumed", measurements=done)
    after_measure = 2 * len(plan.verify_poses) + (0 if options.acceptance is None else 5 * options.acceptance.cycles)
    total = len(plan.measure_poses) + after_measure
    if options.adaptive is not None:  # the best case at first; each forecast updates it
        total = max(done, journal.step("adaptive_best_rows") or 0) + after_measure
    try:
        with terminal_progress(total, done) as (advance, bar, task):
            shown = None if options.adaptive is None else adaptive_lines(bar, task, after_measure)
            engine = Engine(devices, journal, confirm=confirm, on_measure=advance,
                            move_timeout_s=devices.station.motion.move_timeout_s,
                            observer=combine_observers(observer, shown),
                            links=devices.station.links, approach_mm=plan.approach_mm, on_prompt=on_prompt,
                            asking=lambda: bar_aside(bar))
            result: ProcedureResult = engine.run(calibration_procedure(plan, robot, options))
    except RunInterrupted as e:
        journal.set_status("interrupted")
        if options.adaptive is not None:
            write_executed_plan(journal, out_dir, plan, run_id)
        return RunExit(EXIT_INTERRUPTED, run_id, f"run {run_id} stopped: {stop_reason(e)}. The journal is kept; "
                       f"continue with: {resume_command(run_id, out_dir)}")
    pre_rows = journal.measurements(PRE_PHASES)
    if result.recording is not None:  # a run stopped as not identifiable may have too few rows for a recording
        write_recording(out_dir / "recording.csv", result.recording)
    route = None if options.acceptance is None else options.acceptance.route()[0]
    reference = plan
    if options.adaptive is not None:
        plan = write_executed_plan(journal, out_dir, plan, run_id) or plan
    machine_time = None if timing is None else machine_time_report(journal, plan, robot, timing, route)
    drift = stage_parameters(journal, run_id, result, robot, started_at, recorder)
    if options.adaptive is not None and result.adaptive is not None:
        result.adaptive = adaptive_summary(options.adaptive, result, reference, plan)
    signed = None
    if signoff is not None and result.status == "complete":
        signed = signoff_section(signoff, robot, plan, result, pre_rows, run_id,
                                 dt.datetime.now(dt.UTC).isoformat())
    report_path = _write_report(out_dir, run_id, plan, robot, options, result, started_at, journal, machine_time,
                                drift, signed, simulation)
    journal.set_status(result.status)
    if result.status == "not identifiable":
        return RunExit(EXIT_INTERRUPTED, run_id, f"run {run_id} {result.status}: {'; '.join(result.problems)}. "
                       "Nothing identified or uploaded; give the run more time (--max-minutes)", report_path)
    if result.status != "complete":
        said = "" if result.physics is None or not result.physics.findings else (
            " The diagnosis of the run's recording: " + " ".join(result.physics.findings))
        return RunExit(EXIT_INTERRUPTED, run_id, f"run {run_id} {result.status}: {'; '.join(result.problems)}.{said} "
                       "(nothing uploaded; use --force to upload anyway)", report_path)
    if signed is None:
        return RunExit(EXIT_OK, run_id, f"run {run_id} complete", report_path)
    accepted, certificate, lines = finish_certificate(out_dir, report_path)
    journal.event("certificate", path=str(certificate), accepted=accepted)
    return RunExit(EXIT_OK if accepted else EXIT_NOT_ACCEPTED, run_id,
                   "\n".join([f"run {run_id} complete" + ("" if accepted else ", NOT ACCEPTED"), *lines]),
                   report_path, certificate)


def stop_reason(e: RunInterrupted) -> str:
    """Why a run stopped, in words (the engine says "operator declined: QUESTION" for a no)."""
    text = str(e)
    if text.startswith("operator declined: "):
        return f"the operator answered no to the question '{text.removeprefix('operator declined: ')}'"
    return text or "no reason given"


def resume_command(run_id: str, out_dir: Path) -> str:
    """The shell command that continues a run, quoted so it works when pasted (a --sim run needs no --sim)."""
    return shlex.join(["hilcal", "run", "--resume", run_id, "--out", str(out_dir)])


def machine_time_report(journal: Journal, plan: CalibrationPlan, robot: Robot, timing: TimingSection,
                        acceptance_poses: np.ndarray | None = None) -> dict:
    """Estimated time per phase (with the acceptance test's poses, if any) against the journal's phase checkpoints
    (wall clock)."""
    actual: dict[str, float | None] = {}
    for phase in TIMED_PHASES:
        start = journal.step_time(f"checkpoint:phase_start:{phase}")
        end = journal.step_time(f"checkpoint:phase_end:{phase}")
        actual[phase] = end - start if start is not None and end is not None and end >= start else None
    interrupted = journal.count_events("interrupted", "resumed", "resumed_after_pause") > 0
    estimate = estimate_plan(plan, robot, timing.timing(), acceptance_poses=acceptance_poses)
    return time_section(estimate, actual, {**timing.model_dump(), "settle_s": plan.settle_s}, interrupted=interrupted)


def _write_report(out_dir: Path, run_id: str, plan: CalibrationPlan, robot: Robot, options: RunOptions,
                  result: ProcedureResult, started_at: str, journal: Journal, machine_time: dict | None = None,
                  drift: dict | None = None, signoff: dict | None = None, simulation: dict | None = None) -> Path:
    from hilcal.reports.run import RunReport, write_run_report

    verify_rows = journal.measurements(("verify",))
    after_rows = result.after_rows
    comp = result.compensation
    outcome = result.outcomes.get(result.chosen)
    physics = result.physics
    held_out = None if physics is None or physics.predicted_with is None else physics.predicted_with
    if held_out is None and outcome is not None:
        held_out = outcome.after
    report = RunReport(
        status=result.status, run_id=run_id, uploaded=result.upload is not None, estimator=options.estimator,
        robot_name=robot.name, plan_sha256=plan.sha256(), started_at=started_at,
        finished_at=dt.datetime.now(dt.UTC).isoformat(),
        verify_before=_summary(verify_rows), verify_after=_summary(after_rows) if after_rows else None,
        per_pose_before=_per_pose(verify_rows, len(plan.verify_poses)),
        per_pose_after=_per_pose(after_rows, len(plan.verify_poses)) if after_rows else None,
        identifications={k: o.identification for k, o in result.outcomes.items()},
        predicted_after={k: o.after for k, o in result.outcomes.items() if o.after is not None},
        chosen=result.chosen,
        plausibility={"ok": not result.problems, "violations": result.problems,
                      "joint_bound_mm": options.joint_bound_mm, "offset_bound_mm": options.offset_bound_mm},
        compensation={} if comp is None else {
            "mode": comp.mode,
            "uploaded_parameters": {"a_mm": comp.parameters.a.tolist(), "b_mm": comp.parameters.b.tolist(),
                                    "l0_mm": comp.parameters.l0.tolist()},
            "compensation_block": None if result.block is None else result.block.model_dump(),
            "predicted_held_out": None if held_out is None else held_out.brief(),
            "predicted_basis": "the uploaded model against the held-out verification poses measured before the "
                               "upload (not used in the fit); the verification after the upload measures it",
            "uncompensated": None if comp.uncompensated is None else comp.uncompensated.brief(),
            "uncompensated_basis": None if comp.uncompensated is None else (
                "what the leg offsets alone cannot correct of the identified geometry, over 64 workspace poses"),
        },
        physics=None if physics is None else physics.to_json(),
        upload=result.upload,
        machine_time=machine_time,
        links=links_summary(journal),
        stations=stations_summary(journal.measurements((*PRE_PHASES, AFTER_PHASE, ACCEPTANCE_PHASE))),
        drift=drift,
        signoff=signoff,
        adaptive=result.adaptive if isinstance(result.adaptive, dict) and "summary" in result.adaptive else None,
        simulation=simulation,
        warnings=(*result.acquisition, *result.out_of_reach),
    )
    json_path, _ = write_run_report(out_dir, report)
    journal.event("report", path=str(json_path))
    if comp is not None:  # what the run uploaded (or would have), loadable again with `hilcal upload`
        controller_set = to_parameter_set(comp.parameters).model_dump()
        if result.block is not None:
            controller_set["compensation"] = result.block.model_dump()
        (out_dir / "controller_set.json").write_text(json.dumps(controller_set, indent=1))
    return json_path


def _run_info(journal: Journal) -> dict | None:
    try:
        return journal.run_info()
    except Exception:
        return None


def check_new_run(journal: Journal) -> None:
    """ValueError if the run folder already holds a run (a new run needs a folder of its own)."""
    info = _run_info(journal)
    if info is not None:
        raise ValueError(f"{journal.path.parent} already holds run {info['run_id']} ({info['status']}): "
                         f"resume it with --resume {info['run_id']} or choose another --out folder")


def plan_for_run(journal: Journal, plan: CalibrationPlan | None, run_id: str | None, options: dict,
                 new_id: str | None = None) -> tuple[str, CalibrationPlan, dict]:
    """Start a new run in the journal (as ``new_id`` if given), or check and reload the one being resumed."""
    info = _run_info(journal)
    if run_id is not None:
        if info is None or info["run_id"] != run_id:
            found = "no run" if info is None else f"run {info['run_id']}"
            raise ValueError(f"cannot resume {run_id}: {journal.path} holds {found}")
        return run_id, CalibrationPlan.model_validate_json(info["plan_json"]), info["options"]
    check_new_run(journal)
    assert plan is not None
    new_id = new_id or new_run_id()
    journal.start(new_id, plan.sha256(), json.dumps(plan.model_dump()), options)
    save_plan(plan, journal.path.parent / ("reference_plan.json" if options.get("adaptive") else "plan.json"))
    return new_id, plan, options


@dataclass(frozen=True)
class RunRequest:
    """What `hilcal run` was asked to do."""

    out_dir: Path
    sim: bool = False
    station_path: Path | None = None
    sim_config: Path | None = None
    resume: str | None = None
    yes: bool = False
    estimator: str = "ls"
    force: bool = False
    robot_path: Path | None = None
    plan_path: Path | None = None
    seed: int = 0
    records_path: Path | str | None = None
    """The records database: a SQLite path or a URL (None: the station's, else $HILCAL_RECORDS or the default)."""
    operator: str | None = None
    acceptance: str | None = None
    """"iso9283": the ISO 9283 acceptance test after the verification (None: no acceptance test)."""
    cycles: int = 30
    """Cycles of the acceptance test (ISO 9283: 30)."""
    physics: bool = True
    """Diagnose the run's recording and upload the compensation of what it finds (False: the geometry alone)."""
    adaptive: AdaptiveOptions | None = None
    """Measure adaptively (``procedures.adaptive``): until the accuracy is proven, within the whole run's budget."""
    sim_station: SimStation | None = None
    instrument: str | None = None
    """The simulated instrument of a --sim run ("cmm" or "tracker"; None: the simulator configuration's)."""
    timing: TimingSection | None = None
    """The machine's timing for a --sim run (a real run reads the station file's [timing])."""
    on_estimate: Callable[[CalibrationPlan, TimeEstimate, TimingSection], None] | None = None
    """Called with the plan's estimated machine time before anything moves."""
    on_adaptive_estimate: Callable[[AdaptiveRun, dict, TimingSection], None] | None = None
    """An adaptive run's instead: called with its range before motion (``procedures.adaptive.time_range_json``)."""
    on_prompt: Callable[[Any], None] | None = None
    """Called with a procedure prompt before it is asked at the terminal (prints the upload approval's detail)."""
    run_id: str | None = None
    """The id of a new run (None: made when it starts); the command line's default run folder is named after it."""
    timing_source: str | None = None
    """Where the run's timing comes from, in words (printed and in the report of a --sim run)."""
    on_simulation: Callable[[dict], None] | None = None
    """Called with what the simulator simulates once it runs (``SimulatedStation.simulation``, timing added)."""


def default_records_path() -> str:
    """$HILCAL_RECORDS (a path or a URL), else ~/.local/share/hilcal/records.sqlite."""
    from procedures.records import default_target

    return default_target()


def execute_run(req: RunRequest, confirm: Callable[[str], bool] | None, panel: Any = None) -> RunExit:
    """Start or resume a run in req.out_dir; never raises for bad input or device trouble (see RunExit.code).

    A new run that does not start (bad input, a device that does not answer) leaves nothing: what it wrote in its
    folder is removed again (the folder too if it made it), so no journal offers it to ``--resume``.
    """
    from procedures.records import RecordsError, RecordsUnavailable
    from procedures.records.sync import RunRecorder

    recorder = RunRecorder(records_target(req))
    try:
        recorder.open()
    except RecordsError as e:
        return RunExit(EXIT_BAD_INPUT, "", f"records: {e}", started=False)
    except RecordsUnavailable as e:
        return RunExit(EXIT_INTERRUPTED, "", f"{e}. The run did not start and nothing moved: start the database, or "
                       "give --records FILE to record into a local SQLite file", started=False)
    before = set(req.out_dir.iterdir()) if req.out_dir.is_dir() else None
    req.out_dir.mkdir(parents=True, exist_ok=True)
    result = _execute(req, confirm, panel, recorder)
    if not result.started and req.resume is None:
        _remove_new(req.out_dir, before)
    return result


def _remove_new(out_dir: Path, before: set[Path] | None) -> None:
    """Remove what a run that never started wrote: the folder if it did not exist, else the entries it added."""
    if before is None:
        shutil.rmtree(out_dir, ignore_errors=True)
        return
    for entry in set(out_dir.iterdir()) - before:
        if entry.is_dir():
            shutil.rmtree(entry, ignore_errors=True)
        else:
            entry.unlink(missing_ok=True)


def _execute(req: RunRequest, confirm: Callable[[str], bool] | None, panel: Any, recorder: Any) -> RunExit:
    from procedures.station import DeviceOpenError, StationConfigError, load_station, open_devices

    configure_logs(req.out_dir)
    started_at = dt.datetime.now(dt.UTC).isoformat()
    with Journal(req.out_dir / "journal.sqlite") as journal, contextlib.ExitStack() as stack:
        stack.callback(recorder.close)
        run_id, simulation = req.resume, None
        try:
            if req.resume is None:
                check_new_run(journal)
                robot = load_robot(req.robot_path)
                timing = _station_timing(req)
                plan = (load_plan(req.plan_path, robot) if req.plan_path else
                        make_plan(robot, req.seed, timing=timing.timing()))
                test = make_acceptance(robot, plan, req.cycles, req.acceptance) if req.acceptance else None
                options = {"sim": req.sim, "estimator": req.estimator, "force": req.force,
                           "timing": timing.model_dump(), "timing_source": req.timing_source,
                           "operator": req.operator, "acceptance": None if test is None else test.model_dump(),
                           "robot_path": None if req.robot_path is None else str(req.robot_path),
                           "station_path": None if req.station_path is None else str(req.station_path),
                           "sim_config": None if req.sim_config is None else str(req.sim_config),
                           "physics": req.physics, "instrument": req.instrument,
                           "adaptive": None if req.adaptive is None else req.adaptive.model_dump()}
            else:
                run_id, plan, options = plan_for_run(journal, None, req.resume, {})
                robot = load_robot(options["robot_path"])
                timing = TimingSection.model_validate(options.get("timing", {}))
                test = AcceptanceTest.model_validate(options["acceptance"]) if options.get("acceptance") else None
            adaptive = _adaptive_for(plan, robot, timing, options, test)
            shown = _announce(req, journal, plan, robot, timing, test, adaptive)
            if options["sim"]:
                if req.sim_station is None:
                    raise ValueError("this run uses the simulated devices (--sim), but no simulator was given")
                station = stack.enter_context(req.sim_station(options["sim_config"], req.out_dir,
                                                              options["robot_path"], options.get("instrument")))
                if isinstance(station, SimulatedStation):
                    station, simulation = station.station, station.simulation
                if simulation is not None:
                    simulation = {**simulation, "timing": options.get("timing_source")}
                    if req.on_simulation is not None:
                        req.on_simulation(simulation)
            else:
                station = load_station(req.station_path or options["station_path"])
            settings = signoff_settings(options, station)
        except (RobotFileError, PlanError, StationConfigError, ValueError) as e:
            return RunExit(EXIT_BAD_INPUT, run_id or "", str(e), started=run_id is not None)
        except SimulatorStartError as e:
            return RunExit(EXIT_INTERRUPTED, run_id or "", f"the simulated devices did not start: {e}",
                           started=run_id is not None)
        try:
            devices = stack.enter_context(open_devices(station, run_folder=req.out_dir))
        except DeviceOpenError as e:
            if run_id is None:
                return RunExit(EXIT_INTERRUPTED, "", f"the run did not start: cannot connect to {e}. Nothing moved "
                               "and no run was recorded: check the device and its setting in the station file, then "
                               "start the run again", started=False)
            return RunExit(EXIT_INTERRUPTED, run_id, f"run {run_id} cannot continue: cannot connect to {e}. Nothing "
                           f"moved; its journal is kept: once the device answers, continue with: "
                           f"{resume_command(run_id, req.out_dir)}")
        if run_id is None:
            run_id, plan, options = plan_for_run(journal, plan, None, options, new_id=req.run_id)
            if test is not None:
                save_acceptance(test, req.out_dir / "acceptance.json")
        operator = req.operator or options.get("operator") or settings.operator
        if panel is not None:
            from procedures.panel.control import NotStarted

            acceptance_poses = 0 if test is None else 5 * test.cycles
            panel.run_opened(run_id=run_id, plan=plan, robot=robot, out_dir=req.out_dir, journal=journal,
                             devices=devices, resumed=req.resume is not None, acceptance_poses=acceptance_poses,
                             adaptive=shown)
            route = None if test is None else test.route()[0]
            try:
                operator = panel.wait_start(*start_form(plan, robot, timing.timing(), options, route,
                                                        req.resume is None)) or operator
            except (NotStarted, KeyboardInterrupt):
                result = RunExit(EXIT_INTERRUPTED, run_id, f"run {run_id} not started by the operator; start it "
                                 f"later with: {resume_command(run_id, req.out_dir)}")
                panel.finished(code=result.code, message=result.message, status="not started", out_dir=None,
                               report=None)
                return result
            if panel.start_plan is not None and apply_start_plan(panel.start_plan, journal, options, req.out_dir):
                options = journal.run_info()["options"]
                adaptive = _adaptive_for(plan, robot, timing, options, test)
                panel.view.show_plan(plan, robot, acceptance_poses,
                                     _announce(req, journal, plan, robot, timing, test, adaptive))
        run_options = RunOptions(estimator=options["estimator"], force=bool(options["force"]), acceptance=test,
                                 physics=bool(options.get("physics", True)), adaptive=adaptive,
                                 **instrument_options(station, robot))
        record_start(recorder, journal, req, run_id, started_at, robot, plan, operator, run_options.estimator)
        signoff = SignoffContext(operator, settings, test, bool(options["sim"]), options["robot_path"],
                                 station.instrument_address(), station.measuring_tracker(), simulation)
        result = run_with_devices(devices, journal, plan, robot, run_options, req.out_dir, run_id, confirm,
                                  started_at, timing, None if panel is None else panel.observer, recorder, signoff,
                                  None if panel is not None else req.on_prompt, simulation)
        record_outcome(recorder, journal, run_id, operator, result)
        note = record_signoff(recorder, journal, result.report_path, result.certificate_path)
        if note:
            result = dataclasses.replace(result, message=f"{result.message}\n{note}")
        if recorder.message(req.out_dir):
            result = dataclasses.replace(result, message=f"{result.message}\n{recorder.message(req.out_dir)}")
        if panel is not None:
            report = json.loads(result.report_path.read_text()) if result.report_path is not None else None
            panel.finished(code=result.code, message=result.message, status=journal.run_info()["status"],
                           out_dir=req.out_dir, report=report)
        return result


def _announce(req: RunRequest, journal: Journal, plan: CalibrationPlan, robot: Robot, timing: TimingSection,
              test: AcceptanceTest | None, adaptive: AdaptiveRun | None) -> dict | None:
    """Before motion: print the estimate (an adaptive run's range); the adaptive run's options and range."""
    if adaptive is None:
        if req.on_estimate is not None:
            route = None if test is None else test.route()[0]
            req.on_estimate(plan, estimate_plan(plan, robot, timing.timing(), acceptance_poses=route), timing)
        return None
    range_json = time_range_json(adaptive)
    journal.set_step("adaptive_best_rows", range_json["best_rows"])
    if req.on_adaptive_estimate is not None:
        req.on_adaptive_estimate(adaptive, range_json, timing)
    return {**adaptive.options.model_dump(), **range_json}


def _adaptive_for(plan: CalibrationPlan, robot: Robot, timing: TimingSection, options: dict,
                  test: AcceptanceTest | None) -> AdaptiveRun | None:
    """The adaptive problem of a run whose options ask for one (rebuilt alike on resume), else None."""
    if not options.get("adaptive"):
        return None
    return adaptive_run(plan, robot, timing.timing(), AdaptiveOptions.model_validate(options["adaptive"]),
                        None if test is None else test.route()[0])


def _station_timing(req: RunRequest) -> TimingSection:
    """The machine's timing: the station file's [timing] (a real run), or what the caller gives (--sim)."""
    from procedures.station import load_station

    if req.sim:
        return req.timing or TimingSection()
    return load_station(req.station_path).timing if req.station_path else TimingSection()
