"""Commands for the operator at the machine: run (and resume), upload, rollback (history: ``cli/records.py``)."""

from __future__ import annotations

import enum
import functools
from pathlib import Path
from typing import Annotated

import typer
from rich.markup import escape

from procedures.cli.common import EstimatorChoice, err, fail, out
from procedures.cli.panel import DEFAULT_PORT, PortOption
from procedures.cli.records import RecordsOption, open_records
from procedures.cli.signoff import AcceptanceOption, CyclesOption, ask_operator


class PhysicsChoice(enum.StrEnum):
    on = "on"
    off = "off"


class InstrumentChoice(enum.StrEnum):
    cmm = "cmm"
    tracker = "tracker"


class ControllerChoice(enum.StrEnum):
    hilcal = "hilcal"
    canopen = "canopen"
    canopen_cia402 = "canopen-cia402"


RunRobotOption = Annotated[Path | None, typer.Option("--robot", help=(
    "your machine's robot file (TOML; `hilcal robot-from-geometry` writes one); with --sim the simulator runs it. A "
    "station file's robot and a simulator config's must be the same robot (else the run is refused before anything "
    "starts, saying how to fix it); default: theirs, else the built-in paper Table 1 robot"))]
DEFAULT_RUNS = Path("runs")
"""Where a run's folder goes when --out is not given: runs/RUN_ID."""


def run(
    out_dir: Annotated[Path | None, typer.Option("--out", help="run folder: journal, logs, recording, report and "
                                                 "certificate (default: runs/RUN_ID, printed at the start; with "
                                                 "--resume: runs/RUN_ID of that run)")] = None,
    sim: Annotated[bool, typer.Option("--sim", help="start the simulated devices and run against them")] = False,
    station: Annotated[Path | None, typer.Option(help="station file (TOML): the devices' connections, the robot, "
                                                 "\\[timing], \\[acceptance] and who signs off; with --sim only its "
                                                 "robot and sign-off settings are used, and its \\[timing] with "
                                                 "--station-timing")] = None,
    station_timing: Annotated[bool, typer.Option("--station-timing", help="with --sim and --station: plan, estimate "
                                                 "and wait at every pose with the station file's \\[timing] as "
                                                 "written, at the machine's pace (default: the simulated station's "
                                                 "own timing, about 100 times faster)")] = False,
    sim_config: Annotated[Path | None, typer.Option(help="with --sim: the simulator's settings (TOML: robot, "
                                                    "geometric errors, effects, noise, faults; docs/procedure.md)")
                          ] = None,
    instrument: Annotated[InstrumentChoice | None, typer.Option(help="with --sim: measure with the simulated CMM or "
                                                                "laser tracker (default: the simulator config's, "
                                                                "else the CMM); a station file names its own "
                                                                "(\\[instrument] kind)")] = None,
    controller: Annotated[ControllerChoice | None, typer.Option(help="with --sim: the simulated controller's "
                                                                "protocol (hilcal's own, the HX-6 CANopen controller, "
                                                                "or six CiA 402 drives; default: the simulator "
                                                                "config's); a station file names its own "
                                                                "(\\[controller] kind)")] = None,
    resume: Annotated[str | None, typer.Option(help="continue the stopped run RUN_ID (its folder: --out, default "
                                               "runs/RUN_ID)")] = None,
    yes: Annotated[bool, typer.Option("--yes", help="unattended: answer every prompt yes")] = False,
    estimator: Annotated[EstimatorChoice, typer.Option(help="parameters to upload")] = EstimatorChoice.ls,
    force: Annotated[bool, typer.Option("--force", help="upload even a parameter set the plausibility check refuses "
                                        "(corrections beyond a machine's assembly tolerances)")] = False,
    physics: Annotated[PhysicsChoice, typer.Option(help="on: diagnose the run's own recording and upload the "
                                                   "compensation of what it finds with the geometry; off: the "
                                                   "geometry alone")] = PhysicsChoice.on,
    robot: RunRobotOption = None,
    plan: Annotated[Path | None, typer.Option(help="re-run a saved plan.json (an adaptive run's is the plan as it "
                                              "executed it); with --adaptive, its verify poses and its measure poses "
                                              "as the reference")] = None,
    adaptive: Annotated[bool, typer.Option("--adaptive", help="measure one pose at a time, the most informative "
                                           "next, until the accuracy is proven (docs/procedure.md)")] = False,
    target_mm: Annotated[float | None, typer.Option(help="with --adaptive: stop once the predicted verify maximum is "
                                                    "below this with 95 % confidence (mm); without it: when the "
                                                    "prediction stops improving")] = None,
    max_minutes: Annotated[float | None, typer.Option(help="with --adaptive: the whole run's machine time; the verify "
                                                      "phases' estimate is kept for them (default: the fixed plan's "
                                                      "estimate)")] = None,
    seed: Annotated[int, typer.Option(help="seed of the plan's D-optimal design: the same seed, the same poses")] = 0,
    records: RecordsOption = None,
    operator: Annotated[str | None, typer.Option(help="name recorded with the run and on its certificate "
                                                  "(asked for if not given)")] = None,
    acceptance: AcceptanceOption = None,
    cycles: CyclesOption = 30,
    panel: Annotated[bool, typer.Option("--panel", help="serve the operator panel (a web page) for this run")] = False,
    port: PortOption = DEFAULT_PORT,
    panel_host: Annotated[str, typer.Option(help="panel address; other than the loopback needs the printed token")] = (
        "127.0.0.1"),
    panel_linger_min: Annotated[float, typer.Option(help="keep the panel up this long after the run", min=0)] = 30.0,
) -> None:
    """Measure, identify, upload (transactionally), verify and sign off: the whole calibration at the machine.

    Exit codes: 0 complete (and accepted), 2 bad input, 3 stopped (resumable with --resume) or not started (a
    device did not answer), 4 complete but not accepted.
    """
    from procedures.adaptive import AdaptiveError, adaptive_options
    from procedures.cli.panel import run_with_panel
    from procedures.cli.plan_time import print_adaptive_estimate, print_run_estimate
    from procedures.cli.run_summary import print_run_end
    from procedures.cli.run_terminal import (
        announce_robot,
        print_simulation,
        resume_folder,
        run_timing,
        terminal_confirm,
    )
    from procedures.cli.sim_station import sim_station
    from procedures.runner import RunRequest, default_records_path, execute_run, new_run_id

    if resume is None and not sim and station is None:
        fail("give --station FILE for real hardware, or --sim for the simulated devices")
    if instrument is not None and (not sim or resume is not None):
        fail("--instrument chooses the simulated instrument of a new --sim run; a station file names its own "
             "([instrument] kind), and a resumed run keeps the one it started with")
    if controller is not None and (not sim or resume is not None):
        fail("--controller chooses the simulated controller of a new --sim run; a station file names its own "
             "([controller] kind), and a resumed run keeps the one it started with")
    if not adaptive and (target_mm is not None or max_minutes is not None):
        fail("--target-mm and --max-minutes belong to an adaptive run: add --adaptive")
    if resume is not None and adaptive:
        fail("a resumed run continues as it started (its journal holds its plan): leave out --adaptive")
    if station_timing and (not sim or station is None or resume is not None):
        fail("--station-timing applies a station file's [timing] to a new simulated run: give --sim and --station "
             "FILE (a run at the machine always uses its station's [timing]; a resumed run keeps its own)")
    try:
        adaptive_plan = adaptive_options(target_mm, max_minutes) if adaptive else None
    except AdaptiveError as e:
        fail(str(e))
    run_id = None
    if resume is not None:
        out_dir = resume_folder(resume, out_dir or DEFAULT_RUNS / resume)
    elif out_dir is None:
        run_id = new_run_id()
        out_dir = DEFAULT_RUNS / run_id
        out.print(f"run {run_id}: its folder is {out_dir}", highlight=False, markup=False, soft_wrap=True)
    timing, timing_source = (None, None) if not sim or resume is not None else run_timing(
        station, station_timing, instrument is InstrumentChoice.tracker)
    if resume is None:  # a resumed run keeps the robot it started with (its journal holds it)
        robot = _one_robot(robot, station, sim, sim_config)
        robot = None if robot is None else robot.resolve()  # the journal keeps it: a resume may start elsewhere
        if not sim:
            announce_robot(robot, station)
    if operator is None and resume is None and not yes and not panel:
        operator = ask_operator()
    request = RunRequest(out_dir=out_dir, sim=sim, station_path=station, sim_config=sim_config, resume=resume,
                         yes=yes, estimator=estimator.value, force=force, robot_path=robot, plan_path=plan,
                         instrument=None if instrument is None else instrument.value,
                         seed=seed, records_path=records, operator=operator, timing=timing,
                         sim_station=functools.partial(sim_station, controller=None if controller is None else
                                                       controller.value, resume=resume is not None),
                         on_estimate=print_run_estimate, acceptance=None if acceptance is None else acceptance.value,
                         cycles=cycles, physics=physics is PhysicsChoice.on, on_prompt=_print_prompt_detail,
                         adaptive=adaptive_plan, on_adaptive_estimate=print_adaptive_estimate, run_id=run_id,
                         timing_source=timing_source, on_simulation=print_simulation)

    def execute(confirm, session=None):
        result = execute_run(request, confirm, session)
        (out if result.code == 0 else err).print(result.message, highlight=False, markup=False, soft_wrap=True)
        print_run_end(out, result.report_path, result.certificate_path)
        return result

    if panel:
        result = run_with_panel(lambda session: execute(session.confirm, session), host=panel_host, port=port,
                                operator=operator, yes=yes, records=records or default_records_path(),
                                linger_min=panel_linger_min)
    else:
        result = execute(None if yes else terminal_confirm)
    raise typer.Exit(result.code)


def _one_robot(robot: Path | None, station: Path | None, sim: bool, sim_config: Path | None) -> Path | None:
    """The run's robot file: --robot, the station file's robot and a simulator config's robot must be one robot
    (exit 2 naming both, the first difference and the fix otherwise); the machine's when --robot is not given (None:
    the built-in robot).

    At the machine, a station file that names no robot means the built-in robot. A simulator config that names no
    robot simulates the run's robot (`--robot`, else the station file's), so only one that names a robot must agree.
    """
    from procedures.cli.run_terminal import robot_fix
    from procedures.cli.sim_station import simulator_robot
    from procedures.station_robot import BUILT_IN_ROBOT, agreed_robot, named_robot

    sources = [] if robot is None else [(f"--robot {robot}", robot)]
    try:
        named = None if station is None else named_robot(station)
        if named is not None:
            sources.append((f"the robot of the station file {station} ({named})", named))
        elif station is not None and not sim:
            sources.append((f"the station file {station} (it names no robot: {BUILT_IN_ROBOT})", None))
        if sim:
            said, path = simulator_robot(sim_config)
            if path is not None:
                sources.append((said, path))
    except ValueError as e:  # StationConfigError, SimConfigError
        fail(str(e))
    try:
        return agreed_robot(sources)
    except ValueError as e:
        fail(f"{e}. {robot_fix(robot, station, named, sim_config)}")


def _print_prompt_detail(prompt) -> None:
    """Before the terminal asks to approve the upload: the parameter diff, then the findings, predictions and block
    (the progress bar is off the screen meanwhile: ``procedures.run_progress.bar_aside``)."""
    if prompt.key == "upload" and prompt.detail:
        from procedures.approval import approval_lines

        for line in approval_lines(prompt.detail, diff_first=True):
            out.print(line, highlight=False, markup=False, soft_wrap=True)


def _params_client(station: Path):
    """The station's parameter interface: Modbus, or the CANopen controller's (exit 2 for a bad station file, 3 when
    the device cannot be opened)."""
    from hilcal.robot import RobotFileError
    from procedures.sections.controller import open_parameters
    from procedures.station import StationConfigError, load_station

    try:
        config = load_station(station)
    except StationConfigError as e:
        fail(str(e))
    try:
        return open_parameters(config)
    except RobotFileError as e:
        fail(str(e))
    except Exception as e:  # the CAN interface or the device did not answer
        err.print(f"[bold red]cannot open the controller:[/] {escape(str(e))}", highlight=False, markup=True)
        raise typer.Exit(3) from None


def _records(station: Path, records: str | None):
    """The records: --records, else the station file's, else the default (exit 2/3 if unusable)."""
    from procedures.station import StationConfigError, load_station

    if records is None:
        try:
            records = load_station(station).records_target()
        except StationConfigError as e:
            fail(str(e))
    return open_records(records)


def _identity(station: Path) -> dict[str, str | None]:
    """The machine and station an upload or rollback is recorded with (from the station file)."""
    from hilcal.robot import RobotFileError, load_robot
    from procedures.records import machine_identity
    from procedures.station import StationConfigError, load_station

    try:
        config = load_station(station)
    except StationConfigError as e:
        fail(str(e))
    try:
        robot_name: str | None = load_robot(config.robot).name
    except RobotFileError:
        robot_name = None  # the upload needs only [modbus]; the record then names no machine
    return {"machine": machine_identity(robot_name, config.machine.serial), "station": config.name}


def upload(
    params_file: Annotated[Path, typer.Argument(help="parameter set JSON {a_mm, b_mm, l0_mm} with an optional "
                                                "compensation block (a run's controller_set.json)")],
    station: Annotated[Path, typer.Option(help="station TOML (its \\[controller] and \\[modbus] or \\[can] "
                                          "sections are used)")],
    save: Annotated[bool, typer.Option(help="also save to non-volatile memory")] = False,
    yes: Annotated[bool, typer.Option("--yes", help="do not ask for confirmation")] = False,
    records: RecordsOption = None,
    operator: Annotated[str | None, typer.Option(help="name recorded with the upload")] = None,
) -> None:
    """Stand-alone controller parameter upload: validate, show the diff, confirm, upload, read back, record."""
    from drivers.controller.parameter_sets import ParamsError
    from procedures.records import ParameterFileError, UploadDeclined, format_diff, upload_parameter_file

    identity = _identity(station)
    db = _records(station, records)
    client = _params_client(station)
    try:
        with db:
            result = upload_parameter_file(client, params_file, db, operator or "", save, yes,
                                           lambda text: typer.confirm(text, default=False), **identity)
    except ParameterFileError as e:
        fail(str(e))
    except UploadDeclined as e:
        err.print(str(e))
        raise typer.Exit(1) from None
    except ParamsError as e:
        err.print(f"[bold red]upload failed:[/] {escape(str(e))}", highlight=False, markup=True)
        raise typer.Exit(3) from None
    finally:
        client.close()
    out.print(format_diff(result["diff"]), highlight=False)
    record = result["record"] or {}
    out.print(f"outcome: {record.get('outcome', 'unchanged')}; sha256 {result['file_sha256'][:16]}")
    out.print(_machine_words(identity, station), highlight=False, markup=False, soft_wrap=True)


def rollback(
    station: Annotated[Path, typer.Option(help="station TOML (its \\[controller] and \\[modbus] or \\[can] "
                                          "sections are used)")],
    records: RecordsOption = None,
    operator: Annotated[str | None, typer.Option(help="name recorded with the rollback")] = None,
) -> None:
    """Restore the controller's previous parameter set (its backup bank; a CANopen controller: the set before its last
    upload, from the records), and record it."""
    from drivers.controller.parameter_sets import ParamsError
    from procedures.records import rollback_controller

    identity = _identity(station)
    db = _records(station, records)
    client = _params_client(station)
    try:
        with db:
            record = rollback_controller(client, db, operator or "", **identity)
    except ParamsError as e:
        err.print(f"[bold red]rollback failed:[/] {escape(str(e))}", highlight=False, markup=True)
        raise typer.Exit(3) from None
    finally:
        client.close()
    out.print(f"rollback: {record.get('outcome')}")
    out.print(_machine_words(identity, station), highlight=False, markup=False, soft_wrap=True)


def _machine_words(identity: dict[str, str | None], station: Path) -> str:
    """The machine an upload or rollback was recorded for, and from which station file."""
    machine = identity.get("machine") or "no machine (the station file's robot could not be read)"
    return f"recorded for machine {machine}, station {identity.get('station') or station} (station file {station})"
