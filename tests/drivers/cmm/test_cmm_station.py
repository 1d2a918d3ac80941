"""The station's CMM: ``[cmm]`` with its tool and ``[cmm.ippdme]`` settings, and the run folder's
``instrument_transcript.txt`` that ``open_devices(station, run_folder=...)`` keeps, against the simulated devices."""

from __future__ import annotations

import re
from collections.abc import Iterator
from pathlib import Path

import pytest

from drivers.cmm.transcript import TRANSCRIPT_NAME
from procedures.station import StationConfigError, open_devices, station_from_channels, station_from_dict
from sim_devices.sim_config import SimConfig
from sim_devices.simulator import SimHandle, start_sim

pytestmark = pytest.mark.timeout(60)
LINE = re.compile(r"^\d{4}-\d\d-\d\dT\d\d:\d\d:\d\d\.\d{6}\+00:00 ([<>]) (.*)$")


@pytest.fixture(scope="module")
def sim() -> Iterator[SimHandle]:
    with start_sim(SimConfig.model_validate({"rig": {"seed": 4}, "cmm": {"time_scale": 0.0}})) as handle:
        yield handle


def test_the_run_folder_keeps_the_conversation_line_by_line(sim: SimHandle, tmp_path: Path) -> None:
    station = station_from_channels(sim.channels())
    for _ in range(2):  # a resumed run appends
        with open_devices(station, run_folder=tmp_path) as devices:
            devices.instrument.prepare()
    lines = (tmp_path / TRANSCRIPT_NAME).read_text().splitlines()
    parsed = [LINE.match(line) for line in lines]
    assert all(parsed), [line for line, m in zip(lines, parsed, strict=True) if not m][:3]
    sent = [m.group(2) for m in parsed if m.group(1) == ">"]
    received = [m.group(2) for m in parsed if m.group(1) == "<"]
    # the devices close with EndSession (on a pty the CMM cannot tell the client left): no 0008 the second time
    assert [s[6:] for s in sent if "Session" in s] == ["StartSession()", "EndSession()"] * 2
    assert received[:2] == [f"{sent[0][:5]} &", f"{sent[0][:5]} %"]  # exactly as on the wire, CR LF removed
    assert any(r.endswith("# Tool.AvrRadius(1.500000)") for r in received)


def test_the_cmm_section_takes_a_tool_and_the_drivers_settings(sim: SimHandle) -> None:
    data = {"can": {"interface": "virtual", "channel": "x"}, "modbus": {"host": "127.0.0.1"},
            "cmm": {"url": "socket://cmm.lab", "alignment": [0, 0, 0, 0, 0, 0], "tool": "Probe2",
                    "ippdme": {"motion_timeout_s": 20.0, "home": "always"}}}
    station = station_from_dict(data)
    assert station.cmm.tool == "Probe2" and station.cmm.ippdme.motion_timeout_s == 20.0
    with pytest.raises(StationConfigError, match=r"ippdme\.motion_timeout_s"):
        station_from_dict({**data, "cmm": {**data["cmm"], "ippdme": {"motion_timeout_s": -1}}})
    with pytest.raises(StationConfigError, match="serial"):  # the old dialect's settings are gone
        station_from_dict({**data, "cmm": {**data["cmm"], "serial": {"command_timeout_s": 30.0}}})
