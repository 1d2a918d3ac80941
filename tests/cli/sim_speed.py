"""Simulator and station settings for runs whose test does not depend on machine time: the servo moves 1e5 times
faster than real time, the CMM probes (and the laser tracker measures) at once and the station waits no settle time
(its servo has settled long before), so a whole `hilcal run --sim` costs the engine, driver and protocol work only
(docs/benchmarks_run.md);
tests/cli/conftest.py's `instant_plan` is the default plan without the settle wait.
The rig's clock follows the servo's, so its temperature is held (a drift of 1 K/h would be tens of K per second)."""

from __future__ import annotations

import json
from pathlib import Path

from procedures.cli.sim_station import SIM_TIMING

DEVICES_INSTANT = """
[controller]
time_scale = 100000.0
[cmm]
time_scale = 0.0
[tracker]
time_scale = 0.0
"""
"""The servo and the instrument (the CMM, or the tracker) near-instant, for a configuration that has its own [rig] (a
twin's)."""

INSTANT_SIM = DEVICES_INSTANT + """[rig.temperature]
drift_k_per_h = 0.0
amplitude_k = 0.0
"""


def instant_timing() -> str:
    """The simulated station's [timing] section with no settle wait."""
    values = {**SIM_TIMING.model_dump(), "settle_s": 0.0}
    return "[timing]\n" + "".join(f"{key} = {value!r}\n" for key, value in values.items())


def plan_rows(path: Path) -> tuple[int, int]:
    """(measure rows, verify rows) a whole run of this plan file journals: every measure pose with its repeats, and
    the verify poses once before and once after the upload (verify rows counts both)."""
    plan = json.loads(path.read_text())
    return len(plan["measure_poses"]), 2 * len(plan["verify_poses"])
