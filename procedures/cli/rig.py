"""Commands for the test rig: sim (every simulated device on real transports) and demo (in-process calibration)."""

from __future__ import annotations

import functools
import tempfile
from pathlib import Path
from typing import TYPE_CHECKING, Annotated

import typer

from procedures.cli.common import accuracy_table, fail, out, robot_or_fail, write_simulated_recording

if TYPE_CHECKING:
    from hilcal.metrics import AccuracySummary


def sim_command(
    config: Annotated[Path | None, typer.Option(help="simulator settings (TOML: robot, geometric errors, effects, "
                                                "noise, faults; docs/procedure.md)")] = None,
    as_json: Annotated[bool, typer.Option("--json", help="print the channels as one JSON line")] = False,
    state_file: Annotated[Path | None, typer.Option(help="keep controller and rig state in this file")] = None,
    seed: Annotated[int | None, typer.Option(help="rig seed")] = None,
    instrument: Annotated[str | None, typer.Option(
        help="the measuring instrument: cmm (the default) or tracker (a laser tracker on emScon over TCP)")] = None,
    controller: Annotated[str | None, typer.Option(
        help="the controller's protocol: hilcal (the default: hilcal's own CAN messages + Modbus TCP), canopen (the "
             "HX-6 hexapod controller, one CANopen node) or canopen-cia402 (six CiA 402 leg drives)")] = None,
    robot: Annotated[Path | None, typer.Option(help="simulate this robot file (default: the config's robot, else the "
                                               "built-in paper Table 1 robot)")] = None,
    station_out: Annotated[Path | None, typer.Option(help="write a station file wired to these simulated devices "
                                                     "(for `hilcal check --station` and `hilcal run --station` while "
                                                     "the simulator runs)")] = None,
) -> None:
    """Start every simulated device (controller on SLCAN/pty + Modbus TCP or CANopen on SLCAN, CMM on a pty or laser
    tracker on TCP) until Ctrl-C."""
    from sim_devices.launcher import run_sim_process
    from sim_devices.sim_config import CONTROLLER_PROTOCOLS, SimConfigError, load_sim_config

    try:
        if instrument not in (None, "cmm", "tracker"):
            raise SimConfigError(f"--instrument must be cmm or tracker, not {instrument!r}")
        if controller not in (None, *CONTROLLER_PROTOCOLS):
            raise SimConfigError(f"--controller must be one of {', '.join(CONTROLLER_PROTOCOLS)}, not {controller!r}")
        sim_config = load_sim_config(config, state_file=state_file, seed=seed, instrument=instrument,
                                     controller=controller, robot=None if robot is None else robot.resolve())
    except SimConfigError as e:
        fail(str(e))
    write = None if station_out is None else functools.partial(_write_station, station_out, config)
    raise typer.Exit(run_sim_process(sim_config, as_json, on_channels=write))


def _write_station(path: Path, config: Path | None, channels: dict) -> None:
    """The station file of the running simulator: its devices' channels, its robot, its CMM's statement or its
    tracker's (with the driver's timeouts for the simulator's speed)."""
    from procedures.cli.sim_station import sim_controller_section, sim_tracker_driver
    from procedures.station import save_station, station_from_channels

    station = station_from_channels(channels, channels.get("robot_path"), sim_controller_section(channels))
    tracker = station.measuring_tracker()
    if tracker is not None:
        station = station.model_copy(update={"tracker": tracker.model_copy(
            update={"driver": sim_tracker_driver(config)})})
    save_station(station, path)
    print(f"station file {path}: these simulated devices (hilcal check --station {path})", flush=True)


def demo(
    seed: Annotated[int, typer.Option(help="seed of the simulated rig's poses and noise")] = 0,
    out_dir: Annotated[Path | None, typer.Option("--out", help="keep the recording in this folder")] = None,
) -> None:
    """Simulate a rig with the paper's Table 2 errors, calibrate with LS and L-infinity, print the table."""
    from hilcal.calibration import calibrate
    from hilcal.kinematics import Geometry, forward_kinematics
    from hilcal.metrics import AccuracySummary
    from hilcal.recording import read_recording
    from sim_devices.rig.config import load_errors

    rb = robot_or_fail(None)
    folder = out_dir or Path(tempfile.mkdtemp(prefix="hilcal-demo-"))
    folder.mkdir(parents=True, exist_ok=True)
    rec_path = folder / "recording.csv"
    with out.status("simulating 56 poses on the simulated rig"):
        write_simulated_recording(rb, rec_path, seed, "table2", 0.005)
    rec = read_recording(rec_path, rb)
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
    out.print(accuracy_table(f"Verification errors, simulated rig, Table 2 errors (seed {seed})", columns))
    out.print(f"recording: {rec_path}\n'true geom.' = the rig's true parameters, i.e. the CMM-noise floor.")
