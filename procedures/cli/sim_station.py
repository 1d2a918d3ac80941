"""`hilcal run --sim`: start the simulated devices as a subprocess and hand the runner a station wired to them.

The runner knows no simulator; it calls this context manager (``RunRequest.sim_station``) for a new run and for
the resume of a ``--sim`` run alike, so a resumed run re-spawns the simulator on the run's state file. The station
it hands over is what an operator would write down for a real one: the devices' channels, the CMM's identity and
stated uncertainty (the simulator's configuration states them) or the laser tracker's identity, MPE, air and targets,
the tracker driver's timeouts for the simulator's speed, and example acceptance limits. `simulator_robot` is the robot
the simulator will run, which the run's robot must be (``procedures.station.agreed_robot``).
"""

from __future__ import annotations

import contextlib
from collections.abc import Iterator
from pathlib import Path

from drivers.tracker.emscon import EmsconConfig
from procedures.runner import SimulatorStartError
from procedures.signoff import AcceptanceSection
from procedures.station import BUILT_IN_ROBOT, StationConfig, station_from_channels
from procedures.timing import TimingSection
from procedures.tracker_section import TrackerDriver
from sim_devices.launcher import SimStartError, spawn_sim_subprocess, stop_sim_subprocess
from sim_devices.sim_config import load_sim_config

SIM_TIMING = TimingSection(leg_speed_mm_s=5100.0, leg_accel_mm_s2=1e6, settle_s=0.05, cmm_s_per_pose=0.38,
                           move_overhead_s=0.006)
"""The timing of the default simulated station, as an operator would write it down for a real one: measured on
its devices (timed moves and pose measurements, benchmarks/bench_machine_time.py), never read from the simulator's
configuration. `hilcal run --sim --station FILE` uses FILE's [timing] instead."""

SIM_TRACKER_TIMING = SIM_TIMING.model_copy(update={"cmm_s_per_pose": 0.03})
"""The simulated tracker station's: a pose measured in about 0.03 s (docs/benchmarks_tracker.md: about 20 ms of
protocol and fitting with the tracker instant, and its 16.9 s of machine time times the simulator's 0.0005)."""

SIM_ACCEPTANCE = AcceptanceSection(max_position_mm=0.05, rms_position_mm=0.02, max_orientation_deg=0.005,
                                   rms_orientation_deg=0.002)
"""Example limits of the simulated station, on the verification poses after calibration (the docs' example
station's): the demo machine starts at about 1.9 mm and 0.06 deg and fails them, and calibrated meets them with
its uncertainty (docs/certificate.md). No ISO 9283 limits: a run without `--acceptance iso9283` would leave them
not tested. They are the built-in paper robot's: a simulated station on another robot file (a small hexapod, a
twin's machine) sets none. `hilcal run --sim --station FILE` uses FILE's [acceptance] instead."""


SIM_TRACKER_ACCEPTANCE = AcceptanceSection(max_position_mm=0.2, rms_position_mm=0.1, max_orientation_deg=0.01,
                                           rms_orientation_deg=0.005)
"""Example limits of the simulated tracker station: a tracker 4 to 9 m away measures each target to ±(15 µm + 6
µm/m), so a pose scatters about 0.03 mm per axis (ten times the CMM's) and the CMM station's limits could not be
proven (docs/protocols.md)."""
TIMEOUT_FLOOR_S = 2.0
"""The simulated tracker's driver timeouts: its durations times its time scale, at least this (a busy computer)."""


def sim_tracker_driver(sim_config: str | Path | None) -> TrackerDriver:
    """The driver's timeouts for the simulated tracker: a real tracker's defaults times the simulator's time scale
    (its turns, searches and measurements take that much less), at least ``TIMEOUT_FLOOR_S``."""
    scale = load_sim_config(sim_config).tracker.time_scale
    keys = ("command_timeout_s", "initialize_timeout_s", "move_timeout_s", "measure_timeout_s")
    defaults = EmsconConfig()
    return TrackerDriver(**{k: max(TIMEOUT_FLOOR_S, getattr(defaults, k) * scale) for k in keys})


def simulator_robot(sim_config: Path | None) -> tuple[str, Path | None]:
    """The robot the simulator of a ``--sim`` run will run: (where it comes from, in words; its robot file, None for
    the built-in robot). SimConfigError (a ValueError) for a configuration that cannot be read."""
    if sim_config is None:
        return f"the simulator's robot (no --sim-config: {BUILT_IN_ROBOT})", None
    robot = load_sim_config(sim_config).robot  # a relative path is relative to the configuration file
    if robot is None:
        return f"the simulator config {sim_config} (it names no robot: {BUILT_IN_ROBOT})", None
    return f"the robot of the simulator config {sim_config} ({robot})", robot


@contextlib.contextmanager
def sim_station(sim_config: str | None, out_dir: Path, robot_path: str | None, instrument: str | None = None
                ) -> Iterator[StationConfig]:
    """Spawn the simulator (state in ``out_dir/sim_state.json``, log in ``out_dir/sim.log``; ``instrument`` "cmm" or
    "tracker" overrides the configuration's); stop it on exit."""
    args = ["--state-file", str(out_dir / "sim_state.json"), *(["--instrument", instrument] if instrument else [])]
    try:
        proc, channels = spawn_sim_subprocess(sim_config, args, log_path=out_dir / "sim.log")
    except SimStartError as e:
        raise SimulatorStartError(str(e)) from e
    try:
        station = station_from_channels(channels, robot_path)
        tracker = station.measuring_tracker()
        if tracker is not None:
            tracker = tracker.model_copy(update={"driver": sim_tracker_driver(sim_config)})
            station = station.model_copy(update={"tracker": tracker})
        own_robot = robot_path is not None or channels.get("robot_path") is not None
        limits = SIM_ACCEPTANCE if tracker is None else SIM_TRACKER_ACCEPTANCE
        yield station if own_robot else station.model_copy(update={"acceptance": limits})
    finally:
        stop_sim_subprocess(proc)
