"""The `hilcal` command line: run, sim, history, upload, rollback, identify, diagnose, identifiability, design,
simulate, demo.

Exit codes: 0 ok, 2 bad input (robot file, recording, options). Units: mm and degrees.
"""

from __future__ import annotations

import json
import logging
import sys
import tempfile
from enum import StrEnum
from pathlib import Path
from typing import Annotated

import numpy as np
import structlog
import typer
from rich.console import Console
from rich.table import Table

from hilcal.calibration import CalibrationOutcome, calibrate
from hilcal.identification import IdentificationError
from hilcal.kinematics import KinematicsError
from hilcal.metrics import AccuracySummary
from hilcal.recording import RecordingError, read_recording, write_recording
from hilcal.robot import Robot, RobotFileError, load_robot

app = typer.Typer(add_completion=False, no_args_is_help=True, help=__doc__)
out = Console(width=None if sys.stdout.isatty() else 120)
err = Console(stderr=True)

BAD_INPUT = 2


class EstimatorChoice(StrEnum):
    ls = "ls"
    linf = "linf"


class ModelChoice(StrEnum):
    m42 = "42"
    m60 = "60"


RobotOption = Annotated[Path | None, typer.Option("--robot", help="robot TOML file (default: paper Table 1)")]


def _fail(message: str) -> None:
    err.print(f"[bold red]error:[/] {message}", highlight=False)
    raise typer.Exit(BAD_INPUT)


def _robot(path: Path | None) -> Robot:
    try:
        return load_robot(path)
    except RobotFileError as e:
        _fail(str(e))
        raise  # unreachable: _fail exits


@app.callback()
def main(verbose: Annotated[bool, typer.Option("--verbose", "-v", help="structured logs on stderr")] = False) -> None:
    """hilcal: kinematic calibration of 6-6 Gough/Stewart platforms (LS and L-infinity)."""
    structlog.configure(
        wrapper_class=structlog.make_filtering_bound_logger(logging.INFO if verbose else logging.WARNING),
        logger_factory=lambda *_: structlog.PrintLogger(sys.stderr),
    )


def _accuracy_table(title: str, columns: list[tuple[str, AccuracySummary | None]]) -> Table:
    """The paper's Table 7 layout: indicators as rows, (position, orientation) per condition as columns."""
    table = Table(title=title)
    table.add_column("indicator")
    for label, _ in columns:
        table.add_column(f"{label}\npos mm", justify="right")
        table.add_column(f"{label}\nori deg", justify="right")
    for indicator in ("max", "range", "mean", "rms"):
        cells = []
        for _, summary in columns:
            if summary is None:
                cells += ["n/a", "n/a"]
            else:
                cells += [f"{getattr(summary.position_mm, indicator):.4f}",
                          f"{getattr(summary.orientation_deg, indicator):.5f}"]
        table.add_row({"max": "maximum", "range": "range", "mean": "average", "rms": "RMS"}[indicator], *cells)
    return table


def _parameter_table(outcome: CalibrationOutcome) -> Table:
    ident = outcome.identification
    table = Table(title=f"Identified errors ({ident.model}-parameter model, {ident.estimator}, {ident.formulation})")
    table.add_column("parameter")
    table.add_column("value", justify="right")
    table.add_column("std error", justify="right")
    std = ident.std_errors if ident.std_errors is not None else [None] * len(ident.names)
    for name, value, s in zip(ident.names, ident.x, std, strict=True):
        table.add_row(name, f"{value:+.4f}", "" if s is None else f"{s:.4f}")
    return table


@app.command()
def identify(
    recording: Annotated[Path, typer.Argument(help="recording CSV")],
    robot: RobotOption = None,
    estimator: Annotated[EstimatorChoice, typer.Option(help="least squares or L-infinity (minimax)")] = (
        EstimatorChoice.ls
    ),
    model: Annotated[ModelChoice, typer.Option(help="42 rigid parameters, or the paper's 60 (linear)")] = (
        ModelChoice.m42
    ),
    formulation: Annotated[str, typer.Option(help="forward (pose error) or implicit (leg-length error)")] = "forward",
    method: Annotated[str, typer.Option(help="iterated (nonlinear) or one_step (paper's linearization)")] = "",
    as_json: Annotated[bool, typer.Option("--json", help="print one JSON object")] = False,
) -> None:
    """Identify geometric errors on the `measure` rows; report accuracy on the `verify` rows."""
    rb = _robot(robot)
    n_params = 60 if model == ModelChoice.m60 else 42
    chosen_method = method or ("one_step" if model == ModelChoice.m60 else "iterated")
    try:
        rec = read_recording(recording, rb, min_measure_rows=n_params // 6 + 1)
        outcome = calibrate(rec, rb, estimator=estimator.value, model=model.value, formulation=formulation,
                            method=chosen_method)
    except (RecordingError, IdentificationError, KinematicsError) as e:
        _fail(str(e))
    if as_json:
        print(json.dumps(outcome.to_json(), indent=2))
        return
    out.print(_parameter_table(outcome))
    out.print(_accuracy_table(
        f"{recording.name}: {outcome.n_measure} measure rows, {outcome.n_verify} verify rows",
        [("before", outcome.before), (f"after {estimator.value}", outcome.after)],
    ))
    ident = outcome.identification
    out.print(f"fit: max |residual| {ident.max_abs_residual:.4f} mm, RMS {ident.rms_residual:.4f} mm, "
              f"{ident.n_iterations} evaluations, converged={ident.converged}")


@app.command()
def run(
    out_dir: Annotated[Path, typer.Option("--out", help="run folder: journal, logs, recording, report")],
    sim: Annotated[bool, typer.Option("--sim", help="start the simulated devices and run against them")] = False,
    station: Annotated[Path | None, typer.Option(help="station TOML (CAN, Modbus, CMM, robot)")] = None,
    sim_config: Annotated[Path | None, typer.Option(help="simulator TOML for --sim")] = None,
    resume: Annotated[str | None, typer.Option(help="continue the interrupted run RUN_ID in --out")] = None,
    yes: Annotated[bool, typer.Option("--yes", help="unattended: answer every prompt yes")] = False,
    estimator: Annotated[EstimatorChoice, typer.Option(help="parameters to upload")] = EstimatorChoice.ls,
    force: Annotated[bool, typer.Option(help="upload even an implausible parameter set")] = False,
    robot: RobotOption = None,
    plan: Annotated[Path | None, typer.Option(help="re-run a saved plan.json")] = None,
    seed: int = 0,
    records: Annotated[Path | None, typer.Option(help="records database (default $HILCAL_RECORDS)")] = None,
    operator: Annotated[str | None, typer.Option(help="name recorded with the run")] = None,
) -> None:
    """Measure, identify, upload (transactionally) and verify: the whole calibration at the machine."""
    from procedures.runner import RunRequest, execute_run

    if resume is None and not sim and station is None:
        _fail("give --station FILE for real hardware, or --sim for the simulated devices")
    request = RunRequest(out_dir=out_dir, sim=sim, station_path=station, sim_config=sim_config, resume=resume,
                         yes=yes, estimator=estimator.value, force=force, robot_path=robot, plan_path=plan,
                         seed=seed, records_path=records, operator=operator)
    result = execute_run(request, None if yes else (lambda text: typer.confirm(text, default=False)))
    (out if result.code == 0 else err).print(result.message, highlight=False)
    if result.report_path is not None:
        out.print(f"report: {result.report_path} and {result.report_path.with_suffix('.html')}")
    raise typer.Exit(result.code)


@app.command("sim")
def sim_command(
    config: Annotated[Path | None, typer.Option(help="simulator TOML (robot, rig errors, noise, faults)")] = None,
    as_json: Annotated[bool, typer.Option("--json", help="print the channels as one JSON line")] = False,
    state_file: Annotated[Path | None, typer.Option(help="keep controller and rig state in this file")] = None,
    seed: Annotated[int | None, typer.Option(help="rig seed")] = None,
) -> None:
    """Start every simulated device (controller on SLCAN/pty + Modbus TCP, CMM on a pty) until Ctrl-C."""
    from sim_devices.launcher import SimConfigError, load_sim_config, run_sim_process

    try:
        sim_config = load_sim_config(config, state_file=state_file, seed=seed)
    except SimConfigError as e:
        _fail(str(e))
    raise typer.Exit(run_sim_process(sim_config, as_json))


def _params_client(station: Path):
    from drivers.controller_modbus import ControllerParams
    from procedures.station import StationConfigError, load_station

    try:
        mb = load_station(station).modbus
    except StationConfigError as e:
        _fail(str(e))
    return ControllerParams(mb.host, mb.port, serial_port=mb.serial_port, baudrate=mb.baudrate,
                            device_id=mb.device_id, timeout_s=mb.timeout_s)


def _records(path: Path | None):
    from procedures.records import Records
    from procedures.runner import default_records_path

    return Records(path or default_records_path())


@app.command()
def history(
    limit: int = 20,
    records: Annotated[Path | None, typer.Option(help="records database (default $HILCAL_RECORDS)")] = None,
) -> None:
    """Past runs, parameter sets and uploads from the calibration records."""
    from procedures.records import format_history

    with _records(records) as db:
        out.print(format_history(db.history(limit)), highlight=False)


@app.command()
def upload(
    params_file: Annotated[Path, typer.Argument(help="parameter set JSON {a_mm, b_mm, l0_mm}")],
    station: Annotated[Path, typer.Option(help="station TOML (its [modbus] section is used)")],
    save: Annotated[bool, typer.Option(help="also save to non-volatile memory")] = False,
    yes: Annotated[bool, typer.Option("--yes", help="do not ask for confirmation")] = False,
    records: Annotated[Path | None, typer.Option(help="records database")] = None,
    operator: Annotated[str | None, typer.Option(help="name recorded with the upload")] = None,
) -> None:
    """Stand-alone controller parameter upload: validate, show the diff, confirm, upload, read back, record."""
    from drivers.controller_modbus import ParamsError
    from procedures.records import ParameterFileError, UploadDeclined, format_diff, upload_parameter_file

    client = _params_client(station)
    try:
        with _records(records) as db:
            result = upload_parameter_file(client, params_file, db, operator or "", save, yes,
                                           lambda text: typer.confirm(text, default=False))
    except ParameterFileError as e:
        _fail(str(e))
    except UploadDeclined as e:
        err.print(str(e))
        raise typer.Exit(1) from None
    except ParamsError as e:
        err.print(f"[bold red]upload failed:[/] {e}", highlight=False)
        raise typer.Exit(3) from None
    finally:
        client.close()
    out.print(format_diff(result["diff"]), highlight=False)
    record = result["record"] or {}
    out.print(f"outcome: {record.get('outcome', 'unchanged')}; sha256 {result['file_sha256'][:16]}")


@app.command()
def rollback(
    station: Annotated[Path, typer.Option(help="station TOML (its [modbus] section is used)")],
    records: Annotated[Path | None, typer.Option(help="records database")] = None,
    operator: Annotated[str | None, typer.Option(help="name recorded with the rollback")] = None,
) -> None:
    """Restore the controller's previous parameter set (its backup bank), and record it."""
    from drivers.controller_modbus import ParamsError
    from procedures.records import rollback_controller

    client = _params_client(station)
    try:
        with _records(records) as db:
            record = rollback_controller(client, db, operator or "")
    except ParamsError as e:
        err.print(f"[bold red]rollback failed:[/] {e}", highlight=False)
        raise typer.Exit(3) from None
    finally:
        client.close()
    out.print(f"rollback: {record.get('outcome')}")


@app.command()
def diagnose(
    recording: Annotated[Path, typer.Argument(help="recording CSV (real or simulated)")],
    robot: RobotOption = None,
    as_json: Annotated[bool, typer.Option("--json", help="print one JSON object")] = False,
    report: Annotated[Path | None, typer.Option("--report", help="write plots and an HTML page here")] = None,
    alpha: Annotated[float, typer.Option(help="family-wise false-alarm rate")] = 0.05,
    seed: Annotated[int, typer.Option(help="seed of the bootstrap")] = 0,
) -> None:
    """Find the physics the geometric model leaves out: locate, name, model it, show the fit improve."""
    from hilcal.diagnosis import diagnose as run_diagnosis

    if not 0 < alpha < 1:
        _fail("--alpha must lie in (0, 1)")
    rb = _robot(robot)
    try:
        rec = read_recording(recording, rb)
        diag = run_diagnosis(rec, rb, alpha=alpha, seed=seed)
    except (RecordingError, IdentificationError, KinematicsError) as e:
        _fail(str(e))
    page = None
    if report is not None:
        from hilcal.diagnosis_report import write_report

        page = write_report(diag, rec, report, alpha)
    if as_json:
        print(json.dumps(diag.to_json(), indent=2))
        return
    out.print(f"[bold]effect:[/] {diag.effect}")
    out.print(diag.explanation, highlight=False)
    out.print(_accuracy_table("verify poses", [("geometry only", diag.before), ("with effect", diag.after)]))
    axes = ", ".join(f"{k} {v:.4g}" for k, v in diag.residual_rms_by_axis().items())
    out.print(f"geometry-only residual RMS per pose axis: {axes}", highlight=False)
    for finding in diag.findings[:5]:
        out.print(f"  - {finding.text}", highlight=False)
    if page is not None:
        out.print(f"report: {page}")


def _pose_set(rb: Robot, recording: Path | None, design_name: str, seed: int) -> np.ndarray:
    from hilcal import design

    if recording is not None:
        try:
            return read_recording(recording, rb, min_measure_rows=1).select("measure").meas
        except RecordingError as e:
            _fail(str(e))
    sets = design.paper_pose_sets(rb, seed)
    if design_name not in sets:
        _fail(f"unknown pose set {design_name!r}: choose one of {', '.join(sets)}")
    return sets[design_name].poses


@app.command()
def identifiability(
    model: Annotated[ModelChoice, typer.Option(help="42 rigid parameters or the paper's 60")] = ModelChoice.m42,
    robot: RobotOption = None,
    recording: Annotated[Path | None, typer.Option(help="use this recording's measure poses")] = None,
    pose_set: Annotated[str, typer.Option(help="or one of the paper's four pose sets")] = "set3_factorial_exchange32",
    seed: int = 0,
) -> None:
    """Rank, condition number and unidentifiable directions of an error model over a pose set."""
    from hilcal.identifiability import format_report
    from hilcal.identifiability import identifiability as analyse

    rb = _robot(robot)
    poses = _pose_set(rb, recording, pose_set, seed)
    out.print(format_report(analyse(rb, poses, model.value)), highlight=False)


@app.command()
def design(
    robot: RobotOption = None,
    seed: int = 0,
    out_csv: Annotated[Path | None, typer.Option("--out", help="write the chosen pose set as CSV")] = None,
    pose_set: Annotated[str, typer.Option(help="pose set written by --out")] = "set3_factorial_exchange32",
) -> None:
    """D-optimal measurement poses: the paper's four pose sets with log-det, D-efficiency, condition."""
    from hilcal import design as dsg

    rb = _robot(robot)
    sets = dsg.paper_pose_sets(rb, seed)
    out.print(dsg.design_report(list(sets.values())), highlight=False)
    if out_csv is not None:
        if pose_set not in sets:
            _fail(f"unknown pose set {pose_set!r}: choose one of {', '.join(sets)}")
        header = "x_mm,y_mm,z_mm,roll_deg,pitch_deg,yaw_deg"
        np.savetxt(out_csv, sets[pose_set].poses, delimiter=",", header=header, comments="", fmt="%.6f")
        out.print(f"wrote {len(sets[pose_set].poses)} poses of {pose_set} to {out_csv}")


def _simulate(rb: Robot, out_path: Path, seed: int, errors: str, noise_mm: float) -> None:
    from hilcal import design as dsg
    from procedures.simulated_recording import simulate_recording
    from sim_devices.config import RigConfig, load_errors

    try:
        config = RigConfig(seed=seed, errors=load_errors(errors, rb), cmm_noise_mm=noise_mm)
    except (ValueError, OSError) as e:
        _fail(f"--errors {errors}: {e}")
    rng = np.random.default_rng(seed)
    measure = dsg.factorial_exchange(rb, 32, rng).poses
    verify = dsg.verification_poses(rb, 24, seed)
    write_recording(out_path, simulate_recording(rb, config, measure, verify))


@app.command()
def simulate(
    out_path: Annotated[Path, typer.Option("--out", help="recording CSV to write")],
    seed: int = 0,
    errors: Annotated[str, typer.Option(help="errors TOML file or table2|table3|table4|table5|zero")] = "table2",
    noise_mm: Annotated[float, typer.Option("--noise-mm", help="CMM noise std per sphere coordinate, mm")] = 0.005,
    robot: RobotOption = None,
) -> None:
    """Write a recording from the in-process simulated rig (32 D-optimal + 24 verification poses)."""
    if noise_mm < 0:
        _fail("--noise-mm must be >= 0")
    rb = _robot(robot)
    _simulate(rb, out_path, seed, errors, noise_mm)
    out.print(f"wrote {out_path}")


@app.command()
def demo(
    seed: int = 0,
    out_dir: Annotated[Path | None, typer.Option("--out", help="keep the recording in this folder")] = None,
) -> None:
    """Simulate a rig with the paper's Table 2 errors, calibrate with LS and L-infinity, print the table."""
    rb = _robot(None)
    folder = out_dir or Path(tempfile.mkdtemp(prefix="hilcal-demo-"))
    folder.mkdir(parents=True, exist_ok=True)
    rec_path = folder / "recording.csv"
    with out.status("simulating 56 poses on the simulated rig"):
        _simulate(rb, rec_path, seed, "table2", 0.005)
    rec = read_recording(rec_path, rb)
    from hilcal.kinematics import Geometry, forward_kinematics
    from sim_devices.config import load_errors

    ver = rec.select("verify")
    truth = Geometry.nominal(rb).perturbed(load_errors("table2", rb).to_vector())
    floor = AccuracySummary.of(ver.meas, forward_kinematics(truth, ver.legs_mm, ver.meas))
    columns: list[tuple[str, AccuracySummary | None]] = []
    for est in ("ls", "linf"):
        with out.status(f"identifying ({est})"):
            outcome = calibrate(rec, rb, estimator=est)
        if not columns:
            columns.append(("before", outcome.before))
        columns.append((f"after {est}", outcome.after))
    columns.append(("true geom.", floor))
    out.print(_accuracy_table(f"Verification errors, simulated rig, Table 2 errors (seed {seed})", columns))
    out.print(f"recording: {rec_path}\n'true geom.' = the rig's true parameters, i.e. the CMM-noise floor.")


if __name__ == "__main__":
    app()
