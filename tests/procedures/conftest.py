"""Fixtures of the procedure tests: the in-process simulated devices on their real transports."""

from __future__ import annotations

from collections.abc import Iterator

import pytest

from procedures.station import Devices, open_devices, station_from_channels
from sim_devices.sim_config import SimConfig, SimControllerConfig
from sim_devices.simulator import start_sim


@pytest.fixture
def devices() -> Iterator[Devices]:
    """The station's drivers on a simulator whose servo moves in real time (so a test can interrupt a move)."""
    slow = SimConfig(controller=SimControllerConfig(time_scale=1.0))
    with start_sim(slow) as sim, open_devices(station_from_channels(sim.channels())) as devs:
        yield devs
