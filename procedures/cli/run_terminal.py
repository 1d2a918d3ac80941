"""What `hilcal run` says at the terminal before and around the run: the robot it runs, the timing it plans with,
what a simulated run simulates, the fix for two robots that disagree, and the operator's yes or no.

Cheap to import (no numpy): the command imports it when it runs.
"""

from __future__ import annotations

import sys
from pathlib import Path

from procedures.cli.common import fail, out
from procedures.engine import RunInterrupted
from procedures.timing import TimingSection


def run_timing(station: Path | None, station_timing: bool, tracker: bool) -> tuple[TimingSection, str]:
    """A new --sim run's timing and where it comes from, in words: the simulated station's own, or with
    --station-timing the station file's [timing] as written."""
    from procedures.cli.plan_time import timing_or_fail
    from procedures.cli.sim_station import SIM_TIMING, SIM_TRACKER_TIMING

    if station_timing and station is not None:
        timing = timing_or_fail(station)
        return timing, (f"the station file {station}'s [timing] (--station-timing), as written: {timing.describe()}; "
                        "the run waits as the machine would, while the simulated machine's clock runs faster")
    timing = SIM_TRACKER_TIMING if tracker else SIM_TIMING
    source = ("the simulated station's own, as measured on the simulator (about 100 times faster than a machine): "
              f"{timing.describe()}")
    if station is not None:
        source += "; the station file's [timing] is not used (--station-timing uses it)"
    return timing, source


def announce_robot(robot: Path | None, station: Path | None) -> None:
    """At the machine: which robot the run plans, moves and measures with, and where it comes from."""
    from hilcal.robot import RobotFileError, load_robot

    try:
        name = load_robot(robot).name
    except RobotFileError as e:
        fail(str(e))
    where = "the built-in paper Table 1 robot" if robot is None else f"robot file {robot}"
    out.print(f"robot: {name} ({where}" + (f", the machine of station file {station})" if station else ")"),
              highlight=False, markup=False, soft_wrap=True)


def print_simulation(simulation: dict) -> None:
    """A simulated run's machine, in sentences: robot, errors, effects, instrument, clock and the run's timing."""
    from hilcal.reports.run_sections import simulation_lines

    for line in simulation_lines(simulation):
        out.print(line, highlight=False, markup=False, soft_wrap=True)


def resume_folder(run_id: str, out_dir: Path) -> Path:
    """The folder of the run to resume (exit 2 if it holds no run journal, naming where it looked)."""
    if not (out_dir / "journal.sqlite").is_file():
        fail(f"cannot resume {run_id}: {out_dir} holds no run journal (journal.sqlite); give --out with the run's "
             "folder")
    return out_dir


def robot_fix(robot: Path | None, station: Path | None, named: Path | None, sim_config: Path | None) -> str:
    """How to make the places that name a run's robot agree (they name two different robots)."""
    if robot is not None and named is None and station is not None and sim_config is None:
        return (f"To calibrate {robot} at this station, name it in the station file (robot = \"{robot}\"); the "
                "controller holds that machine's geometry")
    others = [] if named is None else [f"the station file ({station})"]
    if sim_config is not None:
        others.append(f"the simulator config ({sim_config})")
    if robot is not None:
        return (f"Fix: leave out --robot to run the robot {' and '.join(others)} names, or make "
                f"{' and '.join(others)} name {robot} (robot = \"...\")")
    return f"Fix: make {' and '.join(others)} name the same robot file (robot = \"...\")"


def terminal_confirm(text: str) -> bool:
    """The operator's answer to a question at the terminal: y or yes, n or no (Enter: no). Standard input closed
    stops the run saying so (RunInterrupted); Ctrl-C pauses it as anywhere else (KeyboardInterrupt)."""
    while True:
        out.print(f"{text} [y/N]: ", end="", highlight=False, markup=False, soft_wrap=True)
        line = sys.stdin.readline()
        if not line:
            out.print()
            raise RunInterrupted(f"standard input closed while asking '{text}'")
        answer = line.strip().lower()
        if answer in ("y", "yes"):
            return True
        if answer in ("", "n", "no"):
            return False
        out.print("answer y or n", highlight=False, markup=False)
