"""The engine's upload of geometry and compensation block against the in-process simulated controller (Modbus TCP):
one transaction, settled by read-back after a crash, never uploaded twice, and rolled back together."""

from __future__ import annotations

import numpy as np
import pytest

from drivers.controller.modbus import CompensationBlock, ModbusTransportError, ParameterSet
from procedures import messages as m
from procedures.engine import Engine, RunInterrupted
from procedures.journal import Journal
from procedures.link_guard import LinksSection
from procedures.station import open_devices, station_from_channels
from sim_devices.sim_config import SimConfig
from sim_devices.simulator import start_sim

pytestmark = pytest.mark.timeout(60)
NO_RETRIES = LinksSection(modbus_retries=0)
"""A dropped Modbus link ends the run at once, as a crash would: the journal is left as the crash leaves it."""


@pytest.fixture
def sim():
    with start_sim(SimConfig()) as handle:
        yield handle


def the_set(live: ParameterSet) -> tuple[ParameterSet, CompensationBlock]:
    new = ParameterSet(a_mm=live.a_mm, b_mm=live.b_mm, l0_mm=(np.array(live.l0_mm) + 0.25).tolist())
    block = CompensationBlock.zero().model_copy(update={"scale_ppm": [-2990.0, 0, 0, 2004.0, 0, 0],
                                                        "compliance_mm_per_kn": [0.006] * 6})
    return new, CompensationBlock.model_validate(block.model_dump())


def upload(new: ParameterSet, block: CompensationBlock):
    yield m.Disable()
    return (yield m.Upload(new, False, block))


def test_an_upload_killed_after_its_commit_is_settled_on_resume_without_a_second_commit(sim, tmp_path) -> None:
    controller = sim.controller
    with open_devices(station_from_channels(sim.channels())) as devices, Journal(tmp_path / "j.sqlite") as journal:
        old_geometry, old_block = devices.params.read_live(), devices.params.read_live_compensation()
        new, block = the_set(old_geometry)
        commit = 1 + 2 + 50 + 1 + 1  # OPEN, the geometry in 2 chunks, the block in 50, the header, then COMMIT
        sim.controller_servers.modbus.faults.drop_connection_at_write(commit, execute=True)
        with pytest.raises(RunInterrupted, match="ModbusTransportError"):
            Engine(devices, journal, links=NO_RETRIES).run(upload(new, block))
        assert journal.step("upload")["outcome"] == "started"
        commits = controller.param_registers()["commit_counter"]
        assert devices.params.read_live_compensation() == block.as_float32()  # the commit went through
        state = Engine(devices, journal).run(upload(new, block))  # the resumed run
        assert state["outcome"] == "committed" and "record" not in state
        assert controller.param_registers()["commit_counter"] == commits, "no second commit"
        assert devices.params.read_live() == new.as_float32()
        devices.params.rollback()  # `hilcal rollback` restores both
        assert devices.params.read_live() == old_geometry and devices.params.read_live_compensation() == old_block


def test_an_upload_killed_before_its_commit_is_done_again_whole(sim, tmp_path) -> None:
    with open_devices(station_from_channels(sim.channels())) as devices, Journal(tmp_path / "j.sqlite") as journal:
        old_geometry, old_block = devices.params.read_live(), devices.params.read_live_compensation()
        new, block = the_set(old_geometry)
        sim.controller_servers.modbus.faults.drop_connection_at_write(30)  # in the middle of the block
        with pytest.raises(RunInterrupted):
            Engine(devices, journal, links=NO_RETRIES).run(upload(new, block))
        assert devices.params.read_live() == old_geometry and devices.params.read_live_compensation() == old_block
        state = Engine(devices, journal).run(upload(new, block))
        assert state["outcome"] == "committed" and state["record"]["compensation_readback_match"]
        assert devices.params.read_live_compensation() == block.as_float32()


def test_a_controller_holding_neither_set_stops_the_run(sim, tmp_path) -> None:
    with open_devices(station_from_channels(sim.channels())) as devices, Journal(tmp_path / "j.sqlite") as journal:
        new, block = the_set(devices.params.read_live())
        Engine(devices, journal).run(upload(new, block))
        journal.set_step("upload", {**journal.step("upload"), "outcome": "started"})
        other = block.model_copy(update={"backlash_mm": [0.01] * 6})
        devices.params.upload(devices.params.read_live(), compensation=other)  # someone else's upload meanwhile
        with pytest.raises(RunInterrupted, match="neither the previous nor the new"):
            Engine(devices, journal).run(upload(new, block))


def test_the_driver_error_reaches_the_link_guard(sim) -> None:
    with open_devices(station_from_channels(sim.channels())) as devices:
        sim.controller_servers.modbus.faults.drop_connection_at_write(1)
        with pytest.raises(ModbusTransportError):
            devices.params.upload(devices.params.read_live(), compensation=CompensationBlock.zero())
