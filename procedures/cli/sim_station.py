"""`hilcal run --sim`: start the simulated devices as a subprocess and hand the runner a station wired to them.

The runner knows no simulator; it calls this context manager (``RunRequest.sim_station``) for a new run and for
the resume of a ``--sim`` run alike, so a resumed run re-spawns the simulator on the run's state file. The station
it hands over is what an operator would write down for a real one: the devices' channels, the CMM's identity and
stated uncertainty (the simulator's configuration states them) or the laser tracker's identity, MPE, air and targets,
the tracker driver's timeouts for the simulator's speed, and example acceptance limits. The simulator runs the run's
robot; `simulator_robot` is the one a simulator config names, which the run's robot must then be
(``procedures.station_robot.agreed_robot``).
"""

from __future__ import annotations

import contextlib
from collections.abc import Iterator
from pathlib import Path
from typing import Any

from drivers.tracker.emscon import EmsconConfig
from procedures.runner import SimulatedStation, SimulatorStartError
from procedures.sections.tracker import TrackerDriver
from procedures.signoff import AcceptanceSection
from procedures.station import station_from_channels
from procedures.timing import TimingSection
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
HX6_MAPPING: dict[str, Any] = {
    "setpoints": {"legs": {"array": "0x2000"}, "apply": "0x2001", "apply_counter": True, "apply_result": "0x2003",
                  "apply_results": {1: "wrong state", 2: "fault active", 3: "e-stop active", 5: "out of limits"}},
    "actual": {"legs": {"array": "0x2010"}},
    "geometry": {"a_mm": {"records": [f"0x{0x2100 + k:04X}" for k in range(6)]},
                 "b_mm": {"records": [f"0x{0x2110 + k:04X}" for k in range(6)]},
                 "l0_mm": {"array": "0x2120"}},
    "compensation": {**{term: {"array": f"0x{0x2201 + k:04X}"} for k, term in enumerate(
        ("scale_ppm", "backlash_mm", "compliance_mm_per_kn", "compliance_mm_per_kn_m", "thermal_ppm_per_k",
         "table_start_mm", "table_end_mm"))},
        "reference_temperature_c": "0x2200:3", "table_points": "0x2200:2",
        "table_mm": [f"0x{0x2210 + k:04X}" for k in range(6)]},
    "readings": {"forces_kn": {"array": "0x2012"}, "temperature_c": "0x2013"},
    "checksum": {"object": "0x2300:1", "algorithm": "crc32-objects"},
    "identity": {"vendor_id": 0x0048434C, "product_code": 0x00060001},
    "emcy_codes": {"0x9000": "e-stop", "0xFF02": "hydraulic pressure"},
}
"""The simulated HX-6's mapping, as its EDS ([Comments]) says where everything is: examples/stations/hx6_sim.toml
holds the same as a station file (tests/cli/test_run_canopen.py checks that they agree)."""
SIM_HEARTBEAT_MS = 20
"""The simulated nodes' producer heartbeat time the station sets (their EDS default is 100 ms)."""
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
    """The robot a simulator config names: (where it comes from, in words; its robot file), None when it names none
    (the simulator then runs the run's robot). SimConfigError (a ValueError) for a configuration that cannot be
    read."""
    if sim_config is None:
        return "no simulator config", None
    robot = load_sim_config(sim_config).robot  # a relative path is relative to the configuration file
    if robot is None:
        return f"the simulator config {sim_config} (it names no robot)", None
    return f"the robot of the simulator config {sim_config} ({robot})", robot


def sim_controller_section(channels: dict[str, Any]) -> dict[str, Any] | None:
    """The station's [controller] for the simulator's CANopen devices (None: hilcal's own protocol)."""
    co = channels.get("canopen")
    if co is None:
        return None
    if co["variant"] == "hexapod":
        return {"kind": "canopen", "eds": co["eds"], "node_id": co["node_ids"][0], "heartbeat_ms": SIM_HEARTBEAT_MS,
                **HX6_MAPPING}
    return {"kind": "canopen", "eds": co["eds"], "node_ids": co["node_ids"], "profile": "cia402-hexapod",
            "position_unit_mm": 0.001, "heartbeat_ms": SIM_HEARTBEAT_MS}


CONTROLLER_FILE = "sim_controller.txt"
"""In a --sim run's folder: the simulated controller's protocol it started with (a resume spawns the same)."""


@contextlib.contextmanager
def sim_station(sim_config: str | None, out_dir: Path, robot_path: str | None, instrument: str | None = None,
                controller: str | None = None, resume: bool = False) -> Iterator[SimulatedStation]:
    """Spawn the simulator of the run's robot (state in ``out_dir/sim_state.json``, log in ``out_dir/sim.log``;
    ``instrument`` "cmm" or "tracker" and ``controller`` "hilcal", "canopen" or "canopen-cia402" override the
    configuration's; a resumed run spawns the controller its run started with); yield its station and what it
    simulates; stop it on exit."""
    chosen = out_dir / CONTROLLER_FILE
    if resume and controller is None and chosen.exists():
        controller = chosen.read_text().strip() or None
    elif not resume:
        out_dir.mkdir(parents=True, exist_ok=True)
        chosen.write_text(controller or "")
    args = ["--state-file", str(out_dir / "sim_state.json"), *(["--instrument", instrument] if instrument else []),
            *(["--controller", controller] if controller else []),
            *(["--robot", str(robot_path)] if robot_path else [])]
    try:
        proc, channels = spawn_sim_subprocess(sim_config, args, log_path=out_dir / "sim.log")
    except SimStartError as e:
        raise SimulatorStartError(str(e)) from e
    try:
        station = station_from_channels(channels, robot_path, sim_controller_section(channels))
        tracker = station.measuring_tracker()
        if tracker is not None:
            tracker = tracker.model_copy(update={"driver": sim_tracker_driver(sim_config)})
            station = station.model_copy(update={"tracker": tracker})
        own_robot = robot_path is not None or channels.get("robot_path") is not None
        limits = SIM_ACCEPTANCE if tracker is None else SIM_TRACKER_ACCEPTANCE
        yield SimulatedStation(station if own_robot else station.model_copy(update={"acceptance": limits}),
                               channels.get("simulation"))
    finally:
        stop_sim_subprocess(proc)
