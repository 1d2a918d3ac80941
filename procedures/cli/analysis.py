"""Commands for the engineer analysing data: identify, diagnose, identifiability, design, simulate.

numpy and the hilcal models (scipy underneath) are imported inside the commands, so `hilcal --help` starts fast.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import TYPE_CHECKING, Annotated

import typer
from rich.markup import escape
from rich.table import Table

from procedures.cli.common import (
    EstimatorChoice,
    ModelChoice,
    RobotOption,
    accuracy_table,
    err,
    fail,
    out,
    robot_or_fail,
    write_simulated_recording,
)
from procedures.cli.signoff import AcceptanceOption, CyclesOption

if TYPE_CHECKING:
    import numpy as np

    from hilcal.calibration import CalibrationOutcome
    from hilcal.recording import Recording
    from hilcal.robot import Robot


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
    from hilcal.calibration import calibrate
    from hilcal.identification import IdentificationError
    from hilcal.kinematics import KinematicsError
    from hilcal.recording import RecordingError, read_recording
    from hilcal.wiring import check_wiring

    rb = robot_or_fail(robot)
    n_params = 60 if model == ModelChoice.m60 else 42
    chosen_method = method or ("one_step" if model == ModelChoice.m60 else "iterated")
    try:
        rec = read_recording(recording, rb, min_measure_rows=n_params // 6 + 1)
    except RecordingError as e:
        fail(str(e))
    wiring = check_wiring(rec.legs_mm, rec.meas, rb)
    if wiring.problem:
        err.print(f"[bold yellow]warning:[/] {escape(wiring.sentence([f'leg{i}_mm' for i in range(1, 7)]))}; "
                  "the identification uses the legs as given (`hilcal diagnose` undoes it)",
                  highlight=False, soft_wrap=True, markup=True)
    try:
        outcome = calibrate(rec, rb, estimator=estimator.value, model=model.value, formulation=formulation,
                            method=chosen_method)
    except (IdentificationError, KinematicsError) as e:
        fail(str(e))
    if as_json:
        print(json.dumps({**outcome.to_json(), "wiring": wiring.to_json()}, indent=2))
        return
    out.print(_parameter_table(outcome))
    out.print(accuracy_table(
        f"{recording.name}: {outcome.n_measure} measure rows, {outcome.n_verify} verify rows",
        [("before", outcome.before), (f"after {estimator.value}", outcome.after)],
    ))
    ident = outcome.identification
    out.print(f"fit: max |residual| {ident.max_abs_residual:.4f} mm, RMS {ident.rms_residual:.4f} mm, "
              f"{ident.n_iterations} evaluations, converged={ident.converged}")
    if ident.misfit is not None and ident.misfit.incomplete:
        out.print(ident.misfit.sentence("the identified errors"), highlight=False, soft_wrap=True)
    hint = _diagnose_hint(rec, outcome)
    if hint:
        out.print(hint, highlight=False, soft_wrap=True)


REPEAT_FACTOR = 3.0
"""A verify error this many times the repeated poses' own scatter is more than noise."""


def _diagnose_hint(rec: Recording, outcome: CalibrationOutcome) -> str | None:
    """When the calibrated verify error is far above the scatter of the recording's repeated poses (or no scatter
    is known), say so and point at `hilcal diagnose`: the geometric model may leave physics or a set-up fault out."""
    import numpy as np

    from hilcal.discovery.noise import find_repeats

    if outcome.after is None:
        return None
    after = outcome.after.position_mm.rms
    groups = find_repeats(rec)
    if not groups:
        return (f"The verify RMS after calibration is {after:.4f} mm; the recording has no repeated poses, so its "
                "noise is unknown here. If that is above your instrument's noise, `hilcal diagnose` looks for what "
                "the geometric model leaves out (missing physics, set-up faults).")
    deviations = np.concatenate([rec.meas[g, :3] - rec.meas[g, :3].mean(axis=0) for g in groups])
    dof = sum(len(g) - 1 for g in groups)
    scatter = float(np.sqrt(np.sum(deviations**2) / dof))
    if after <= REPEAT_FACTOR * scatter:
        return None
    return (f"The verify RMS after calibration, {after:.4f} mm, is {after / scatter:.0f} times the scatter of the "
            f"recording's repeated poses ({scatter:.4f} mm, {len(groups)} group(s)): the geometric model leaves "
            "something out. `hilcal diagnose` names it (missing physics, set-up faults).")


def diagnose(
    recording: Annotated[Path, typer.Argument(help="recording CSV (real or simulated)")],
    robot: RobotOption = None,
    as_json: Annotated[bool, typer.Option("--json", help="print one JSON object")] = False,
    report: Annotated[Path | None, typer.Option("--report", help="write plots, tables, an HTML page and the digital "
                                                "twin (sim_config.toml) here")] = None,
    cmm_sigma_mm: Annotated[float | None, typer.Option(
        "--cmm-sigma-mm", help="CMM sphere-centre uncertainty (mm, 1 sigma per coordinate): the noise yardstick",
    )] = None,
    pose_sigma_mm: Annotated[float | None, typer.Option(
        "--pose-sigma-mm", help="stated pose noise of the instrument (mm, 1 sigma per position coordinate), e.g. a "
        "tracker's 6-DoF probe; with --pose-sigma-deg",
    )] = None,
    pose_sigma_deg: Annotated[float | None, typer.Option(
        "--pose-sigma-deg", help="stated orientation noise (degrees, 1 sigma per axis); with --pose-sigma-mm",
    )] = None,
    alpha: Annotated[float, typer.Option(help="false-alarm rate on a recording without missing physics")] = 0.02,
    seed: Annotated[int, typer.Option(help="seed of the bootstrap")] = 0,
    include_unconfirmed: Annotated[bool, typer.Option(
        "--include-unconfirmed", help="keep the corrections of steps that made the held-out verify poses worse in "
        "the compensation set (left out by default)",
    )] = False,
) -> None:
    """Find the physics the geometric model leaves out: locate, name, model it, show the fit improve."""
    from hilcal.discovery.search import diagnose as run_diagnosis
    from hilcal.identification import IdentificationError
    from hilcal.kinematics import KinematicsError
    from hilcal.recording import RecordingError, read_recording

    if not 0 < alpha < 1:
        fail("--alpha must lie in (0, 1)")
    if cmm_sigma_mm is not None and not cmm_sigma_mm > 0:
        fail("--cmm-sigma-mm must be a positive length in mm")
    if (pose_sigma_mm is None) != (pose_sigma_deg is None):
        fail("--pose-sigma-mm and --pose-sigma-deg go together: give the instrument's position and orientation noise")
    pose_sigma = None if pose_sigma_mm is None else (pose_sigma_mm, pose_sigma_deg)
    if pose_sigma is not None and not (pose_sigma[0] > 0 and pose_sigma[1] > 0):
        fail("--pose-sigma-mm and --pose-sigma-deg must be positive (mm and degrees)")
    rb = robot_or_fail(robot)
    try:
        rec = read_recording(recording, rb)
        diag = run_diagnosis(rec, rb, alpha=alpha, seed=seed, cmm_sigma_mm=cmm_sigma_mm, pose_sigma=pose_sigma,
                             include_unconfirmed=include_unconfirmed)
    except (RecordingError, IdentificationError, KinematicsError) as e:
        fail(str(e))
    page, twin_json = None, None
    if report is not None:
        from hilcal.reports.diagnosis import write_report
        from procedures.cli.twin import compare, write_twin

        try:
            twin = write_twin(diag, rec, rb, robot, report)
            comparison = compare(twin, diag, rec, rb)
        except (ValueError, RuntimeError) as e:
            fail(f"the digital twin could not be made: {e}")
        page = write_report(diag, report, comparison, twin.notes)
        twin_json = comparison.to_json()
    if as_json:
        print(json.dumps({**diag.to_json(), **({"twin": twin_json} if twin_json is not None else {})}, indent=2))
        return
    out.print(f"[bold]effect:[/] {escape(diag.effect)}   [bold]effects:[/] {escape(', '.join(diag.effects) or 'none')}",
              markup=True)
    for sentence in diag.summary:
        out.print(f"  - {sentence}", highlight=False, markup=False)
    if diag.parameter_table:
        params = Table(title="named effects: parameters")
        for col in ("effect", "leg", "value", "unit", "± std error", "grade"):
            params.add_column(col, justify="left" if col in ("effect", "unit", "grade") else "right")
        for r in diag.parameter_table:
            params.add_row(r.effect, "" if r.leg is None else str(r.leg), f"{r.value:+.4g}", r.unit,
                           f"{r.std_error:.2g}", r.grade)
        out.print(params)
    out.print(diag.evidence, highlight=False, markup=False)
    if diag.steps:
        table = Table(title="selection steps")
        for col in ("step", "group", "F", "p", "CV µm", "verify RMS mm", "held out", "removed"):
            table.add_column(col, justify="left" if col in ("group", "held out", "removed") else "right")
        for s in diag.steps:
            held = {None: "", True: "confirmed", False: "NOT confirmed"}[s.confirmed]
            table.add_row(str(s.index), s.key, f"{s.f_statistic:.1f}", f"{s.p_value:.3g}", f"{s.cv_rms_mm * 1000:.2f}",
                          "" if s.verify is None else f"{s.verify.position_mm.rms:.4f}", held, ", ".join(s.removed))
        out.print(table)
    out.print(accuracy_table("verify poses (held out)", [("geometry only", diag.before), ("final model", diag.after)]))
    if diag.findings:
        out.print("Where the geometry-only residual lives (each leg's residual before any effect is fitted, against "
                  "the pose and leg variables; the effects above may explain these):", highlight=False)
    for finding in diag.findings[:5]:
        out.print(f"  - {finding.text}", highlight=False)
    if page is not None:
        out.print(comparison.sentence(), highlight=False, markup=False)
        out.print(f"report: {page} (the digital twin: {report / 'sim_config.toml'})")


def _pose_set(rb: Robot, recording: Path | None, design_name: str, seed: int) -> tuple[np.ndarray, np.ndarray | None]:
    """The poses to analyse and, from a recording with a station column, their instrument stations."""
    from hilcal.planning import design
    from hilcal.recording import RecordingError, read_recording

    if recording is not None:
        try:
            mea = read_recording(recording, rb, min_measure_rows=1).select("measure")
        except RecordingError as e:
            fail(str(e))
        return mea.meas, mea.stations
    if design_name not in design.PAPER_POSE_SETS:
        fail(f"unknown pose set {design_name!r}: choose one of {', '.join(design.PAPER_POSE_SETS)}")
    return design.paper_pose_sets(rb, seed, [design_name])[design_name].poses, None


def identifiability(
    model: Annotated[ModelChoice, typer.Option(help="42 rigid parameters or the paper's 60")] = ModelChoice.m42,
    robot: RobotOption = None,
    recording: Annotated[Path | None, typer.Option(help="use this recording's measure poses")] = None,
    pose_set: Annotated[str, typer.Option(help="or one of the paper's four pose sets")] = "set3_factorial_exchange32",
    seed: Annotated[int, typer.Option(help="seed of the random and D-optimal pose sets")] = 0,
) -> None:
    """Rank, condition number and unidentifiable directions of an error model over a pose set."""
    from hilcal.identifiability import format_report
    from hilcal.identifiability import identifiability as analyse

    rb = robot_or_fail(robot)
    poses, stations = _pose_set(rb, recording, pose_set, seed)
    out.print(format_report(analyse(rb, poses, model.value, stations=stations if model.value == "42" else None)),
              highlight=False)


def design(
    robot: RobotOption = None,
    seed: Annotated[int, typer.Option(help="seed of the D-optimal design: the same seed, the same poses")] = 0,
    out_csv: Annotated[Path | None, typer.Option("--out", help="write the chosen pose set as CSV")] = None,
    pose_set: Annotated[str, typer.Option(help="pose set written by --out")] = "set3_factorial_exchange32",
    station: Annotated[Path | None, typer.Option(help="station file (TOML): its robot is the one planned (unless "
                                                 "--robot), its \\[timing] gives the machine's speed")] = None,
    max_minutes: Annotated[float | None, typer.Option("--max-minutes", help="time budget of the whole run")] = None,
    noise_mm: Annotated[float, typer.Option("--noise-mm", help="pose noise per component for the predicted "
                                            "verify error, mm")] = 0.005,
    plan_out: Annotated[Path | None, typer.Option("--plan-out", help="write the calibration plan (JSON) for "
                                                  "`hilcal run --plan`")] = None,
    n_verify: Annotated[int, typer.Option("--n-verify", help="verification poses of the plan")] = 24,
    acceptance: AcceptanceOption = None,
    cycles: CyclesOption = 30,
) -> None:
    """D-optimal measurement poses (the paper's four pose sets), the calibration plan's order and machine time.

    With --acceptance iso9283: the ISO 9283 test poses P1-P5 and the acceptance test's machine time instead.

    With --max-minutes: the most informative plan that fits, with its D-efficiency and predicted verify error
    (the paper's pose sets are then left out).
    """
    import numpy as np

    from hilcal.planning import design as dsg
    from procedures.cli.plan_time import design_plan, timing_or_fail
    from procedures.cli.signoff import print_acceptance_design

    if noise_mm <= 0 or n_verify < 1 or (max_minutes is not None and max_minutes <= 0):
        fail("--noise-mm, --n-verify and --max-minutes must be positive")
    rb = _design_robot(robot, station)
    timing = timing_or_fail(station)
    if acceptance is not None:
        print_acceptance_design(rb, seed, timing, cycles)
        return
    if max_minutes is not None and out_csv is None:
        design_plan(rb, seed, timing, max_minutes, noise_mm, plan_out, n_verify)
        return
    sets = dsg.paper_pose_sets(rb, seed)
    out.print(dsg.design_report(list(sets.values())), highlight=False)
    if out_csv is not None:
        if pose_set not in sets:
            fail(f"unknown pose set {pose_set!r}: choose one of {', '.join(sets)}")
        header = "x_mm,y_mm,z_mm,roll_deg,pitch_deg,yaw_deg"
        np.savetxt(out_csv, sets[pose_set].poses, delimiter=",", header=header, comments="", fmt="%.6f")
        out.print(f"wrote {len(sets[pose_set].poses)} poses of {pose_set} to {out_csv}")
    design_plan(rb, seed, timing, max_minutes, noise_mm, plan_out, n_verify)


def _design_robot(robot: Path | None, station: Path | None) -> Robot:
    """The robot to plan for: --robot, else the station file's, else the built-in one (exit 2 if --robot and the
    station's are not the same robot); printed with where it comes from."""
    from procedures.station_robot import BUILT_IN_ROBOT, agreed_robot, named_robot

    named = None
    try:
        named = None if station is None else named_robot(station)
        sources = [(f"--robot {robot}", robot)] if robot is not None else []
        if named is not None:
            sources.append((f"the robot of the station file {station} ({named})", named))
        path = agreed_robot(sources)
    except ValueError as e:
        fix = "" if named is None else f" Fix: leave out --robot to plan the station's robot, or name {robot} in it"
        fail(f"{e}.{fix}")
    rb = robot_or_fail(path)
    where = (f"robot file {path}" if path is not None else BUILT_IN_ROBOT) + (
        f", the robot of the station file {station}" if named is not None and robot is None else "")
    out.print(f"robot: {rb.name} ({where})", highlight=False, markup=False, soft_wrap=True)
    return rb


def simulate(
    out_path: Annotated[Path, typer.Option("--out", help="recording CSV to write")],
    seed: Annotated[int, typer.Option(help="seed of the poses and of the simulated noise")] = 0,
    errors: Annotated[str, typer.Option(help="errors TOML file or table2|table3|table4|table5|zero")] = "table2",
    noise_mm: Annotated[float, typer.Option("--noise-mm", help="CMM noise std per sphere coordinate, mm")] = 0.005,
    robot: RobotOption = None,
    sim_config: Annotated[Path | None, typer.Option(
        "--sim-config", help="simulator TOML (e.g. the digital twin `hilcal diagnose --report` writes): its robot "
        "and rig replace --robot, --errors and --noise-mm")] = None,
) -> None:
    """Write a recording from the in-process simulated rig (32 D-optimal + 24 verification poses)."""
    if noise_mm < 0:
        fail("--noise-mm must be >= 0")
    if sim_config is not None:
        _simulate_config(sim_config, out_path, seed)
        out.print(f"wrote {out_path}")
        return
    rb = robot_or_fail(robot)
    write_simulated_recording(rb, out_path, seed, errors, noise_mm)
    out.print(f"wrote {out_path}")


def _simulate_config(path: Path, out_path: Path, seed: int) -> None:
    """`hilcal simulate --sim-config`: the configuration's robot and rig walked through the plan."""
    import numpy as np

    from hilcal.planning import design as dsg
    from hilcal.recording import write_recording
    from procedures.cli.simulated_recording import simulate_recording
    from sim_devices.sim_config import SimConfigError, load_sim_config

    try:
        config = load_sim_config(path)
    except SimConfigError as e:
        fail(str(e))
    rb = robot_or_fail(config.robot)
    try:
        rig = config.rig.rig_config(rb)
    except (ValueError, OSError) as e:
        fail(f"--sim-config {path}: {e}")
    rng = np.random.default_rng(seed)
    measure = dsg.factorial_exchange(rb, 32, rng).poses
    write_recording(out_path, simulate_recording(rb, rig, measure, dsg.verification_poses(rb, 24, seed)))
