"""The compensation block over Modbus TCP: the real driver against the simulated controller, one transaction with the
geometry (staged, CRC'd, committed, backed up, saved, rolled back together), and everything it must refuse.

Block contents are checked with a plain pymodbus client, ``struct`` (float32 ABCD) and ``zlib``'s CRC-32, from the
layout in docs/protocols.md, independently of the driver's and the simulator's encoding.
"""

from __future__ import annotations

import struct
import zlib
from collections.abc import Callable, Iterator
from contextlib import ExitStack
from dataclasses import dataclass

import numpy as np
import pytest
from pymodbus.client import ModbusTcpClient

from drivers.controller.modbus import (
    CapabilityError,
    CompensationBlock,
    ControllerParams,
    ModbusTransportError,
    ParameterValidationError,
    ReadbackMismatch,
)
from hilcal.protocols.registers import ParamStatus
from hilcal.robot import Robot
from sim_devices.controller.modbus_server import ModbusTcpServer
from sim_devices.controller.state_machine import ControllerSimConfig, SimulatedController
from sim_devices.rig.config import GeometryErrors, RigConfig
from sim_devices.rig.rig import SimulatedRig

pytestmark = pytest.mark.timeout(60)

# from docs/protocols.md
LIVE, BACKUP, SAVED = 0x0100, 0x0300, 0x0400
COMP_LIVE, COMP_STAGING, COMP_BACKUP, COMP_SAVED = 0x1000, 0x2000, 0x3000, 0x4000
BLOCK_REGISTERS, LEG_FLOATS, TABLE_SLOTS = 3160, 263, 256
STAGED_LENGTH, LIVE_COMP_CRC32, PARAM_COMMAND, PARAM_STATUS = 0x0030, 0x0038, 0x0020, 0x0021
LEG_FORCES, LEG_TEMPERATURE = 0x0040, 0x004C
OPEN_STAGING, COMMIT = 1, 2


class Raw:
    """A plain pymodbus client reading the documented layout."""

    def __init__(self, port: int) -> None:
        self.client = ModbusTcpClient("127.0.0.1", port=port, timeout=1.0, retries=0)

    def read(self, address: int, count: int) -> list[int]:
        out: list[int] = []
        for start in range(address, address + count, 125):
            n = min(125, address + count - start)
            response = self.client.read_holding_registers(start, count=n, device_id=1)
            assert not response.isError(), response
            out += list(response.registers)
        return out

    def write(self, address: int, values: list[int]) -> int | None:
        response = (self.client.write_register(address, values[0], device_id=1) if len(values) == 1 else
                    self.client.write_registers(address, values, device_id=1))
        return response.exception_code if response.isError() else None

    def block(self, address: int) -> dict[str, object]:
        """A compensation bank decoded by hand: header, then per leg seven float32 scalars and 256 table slots."""
        words = self.read(address, BLOCK_REGISTERS)
        floats = struct.unpack(f">{(BLOCK_REGISTERS - 2) // 2}f", struct.pack(f">{BLOCK_REGISTERS - 2}H",
                                                                             *words[2:]))
        t_ref, legs = floats[0], np.array(floats[1:]).reshape(6, LEG_FLOATS)
        return {"format": words[0], "points": words[1], "t_ref": t_ref, "scalars": legs[:, :7],
                "table": legs[:, 7:], "crc": zlib.crc32(struct.pack(f">{BLOCK_REGISTERS}H", *words))}


@dataclass
class Station:
    controller: SimulatedController
    server: ModbusTcpServer
    params: ControllerParams
    raw: Raw


@pytest.fixture
def make_station(robot: Robot) -> Iterator[Callable[..., Station]]:
    stack = ExitStack()

    def make(**config: object) -> Station:
        rig = SimulatedRig(robot, RigConfig(seed=5, errors=GeometryErrors.zero()))
        controller = SimulatedController(robot, rig, ControllerSimConfig(**config))
        server = ModbusTcpServer(controller).start()
        stack.callback(server.close)
        params = ControllerParams("127.0.0.1", server.port)
        stack.callback(params.close)
        raw = Raw(server.port)
        stack.callback(raw.client.close)
        return Station(controller, server, params, raw)

    yield make
    stack.close()


def a_block(points: int = 17, compliance: float = 0.004, thermal: float = 0.0) -> CompensationBlock:
    rng = np.random.default_rng(7)
    return CompensationBlock(
        scale_ppm=[300.0, -120.0, 0.0, 45.5, 0.0, -2987.0], backlash_mm=[0.02] * 6,
        compliance_mm_per_kn=[compliance] * 6, compliance_mm_per_kn_m=[0.001, 0, 0, 0, 0, 0.002],
        thermal_ppm_per_k=[thermal] * 6, table_start_mm=[10.0] * 6, table_end_mm=[900.0] * 6,
        table_mm=rng.normal(0.0, 0.003, (6, points)).tolist(),
    )


def geometry(robot: Robot, shift_mm: float = 0.25) -> np.ndarray:
    return np.concatenate([robot.a.ravel(), robot.b.ravel(), robot.l0 + shift_mm])


def test_geometry_and_block_commit_together_and_read_back(make_station: Callable[..., Station], robot: Robot
                                                          ) -> None:
    st = make_station()
    before = st.raw.block(COMP_LIVE)
    assert before["format"] == 1 and before["points"] == 0 and not np.any(before["scalars"])
    block = a_block()
    record = st.params.upload(geometry(robot), compensation=block)
    assert record.outcome == "committed" and record.live_readback_match and record.compensation_readback_match
    live = st.raw.block(COMP_LIVE)
    assert live["points"] == 17 and live["t_ref"] == 20.0
    np.testing.assert_array_equal(live["scalars"][:, 0], np.float32(block.scale_ppm))
    np.testing.assert_array_equal(live["scalars"][:, 3], np.float32(block.compliance_mm_per_kn_m))
    np.testing.assert_array_equal(live["table"][:, :17], np.float32(block.table_mm))
    assert not np.any(live["table"][:, 17:])
    assert st.raw.read(LIVE_COMP_CRC32, 2) == [live["crc"] >> 16, live["crc"] & 0xFFFF]
    assert record.compensation_crc32 == f"{live['crc']:08x}"
    assert st.raw.block(COMP_BACKUP)["crc"] == before["crc"]
    assert st.raw.block(COMP_SAVED)["crc"] == before["crc"]  # saving is a separate step
    assert st.params.read_live_compensation() == block.as_float32()
    st.params.save()
    assert st.raw.block(COMP_SAVED)["crc"] == live["crc"]


def test_rollback_restores_geometry_and_block(make_station: Callable[..., Station], robot: Robot) -> None:
    st = make_station()
    old_geometry, old_block = st.params.read_live(), st.raw.block(COMP_LIVE)
    st.params.upload(geometry(robot), compensation=a_block())
    record = st.params.rollback()
    assert record.outcome == "rolled_back" and record.compensation_readback_match
    assert st.params.read_live() == old_geometry and st.raw.block(COMP_LIVE)["crc"] == old_block["crc"]
    st.params.rollback()  # and forward again: a rollback is a swap
    assert st.params.read_live_compensation() == a_block().as_float32()


def test_a_geometry_only_upload_keeps_the_block(make_station: Callable[..., Station], robot: Robot) -> None:
    """A register-map 1.0 host writes the geometry alone: the block stays as it is, and rollback keeps the pair."""
    st = make_station()
    st.params.upload(geometry(robot, 0.1), compensation=a_block())
    kept = st.raw.block(COMP_LIVE)["crc"]
    st.params.upload(geometry(robot, 0.2))
    assert st.raw.block(COMP_LIVE)["crc"] == kept
    np.testing.assert_allclose(st.params.read_live().l0_mm, robot.l0 + 0.2, atol=1e-3)


def test_a_connection_dropped_anywhere_leaves_the_old_pair(make_station: Callable[..., Station], robot: Robot
                                                           ) -> None:
    st = make_station()
    old_geometry, old_crc = st.params.read_live(), st.raw.block(COMP_LIVE)["crc"]
    n_writes = len(st.params.upload(geometry(robot), compensation=a_block()).writes)
    st.params.rollback()
    assert n_writes == 2 + 2 + 50 + 1  # OPEN, geometry in 2 chunks, block in 50 chunks of 64, header, COMMIT
    for n in (1, 2, 3, 20, 52, 53, 54, n_writes):
        st.server.faults.drop_connection_at_write(n, execute=False)
        with pytest.raises(ModbusTransportError):
            st.params.upload(geometry(robot), compensation=a_block())
        assert st.params.read_live() == old_geometry, n
        assert st.raw.block(COMP_LIVE)["crc"] == old_crc, n


def test_a_corrupted_block_write_is_not_committed(make_station: Callable[..., Station], robot: Robot) -> None:
    st = make_station()
    old_crc = st.raw.block(COMP_LIVE)["crc"]
    st.server.faults.corrupt_next_write(1, skip=2)  # the geometry's two chunks pass, the block's first is hit
    with pytest.raises(ReadbackMismatch, match="compensation staging"):
        st.params.upload(geometry(robot), compensation=a_block())
    assert st.raw.block(COMP_LIVE)["crc"] == old_crc


def test_the_controller_checks_the_staged_block(make_station: Callable[..., Station], robot: Robot) -> None:
    """By hand, past the driver: a wrong block CRC, an out-of-bounds value and a term without its sensor."""
    st = make_station(temperature_reading=False)
    good = a_block()
    geometry_words = st.params.read_live().to_words()

    def stage(words: list[int], comp_crc: int) -> int:
        assert st.raw.write(PARAM_COMMAND, [OPEN_STAGING]) is None
        st.raw.write(0x0200, geometry_words[:64])
        st.raw.write(0x0240, geometry_words[64:])
        for k in range(0, BLOCK_REGISTERS, 100):
            st.raw.write(COMP_STAGING + k, words[k:k + 100])
        crc = zlib.crc32(struct.pack(">84H", *geometry_words))
        st.raw.write(STAGED_LENGTH, [84 + BLOCK_REGISTERS, crc >> 16, crc & 0xFFFF, comp_crc >> 16,
                                     comp_crc & 0xFFFF])
        st.raw.write(PARAM_COMMAND, [COMMIT])
        return st.raw.read(PARAM_STATUS, 1)[0]

    words = good.to_words()
    crc = zlib.crc32(struct.pack(f">{BLOCK_REGISTERS}H", *words))
    assert stage(words, crc ^ 1) == ParamStatus.CRC_MISMATCH
    bad = list(words)
    bad[4:6] = struct.unpack(">2H", struct.pack(">f", 200_000.0))  # leg 1 scale beyond ±10 %
    assert stage(bad, zlib.crc32(struct.pack(f">{BLOCK_REGISTERS}H", *bad))) == ParamStatus.LIMIT_VIOLATION
    warm = a_block(thermal=11.5).to_words()
    assert stage(warm, zlib.crc32(struct.pack(f">{BLOCK_REGISTERS}H", *warm))) == ParamStatus.NOT_SUPPORTED
    assert st.raw.block(COMP_LIVE)["points"] == 0  # nothing committed
    assert stage(words, crc) == ParamStatus.OK


def test_blocks_a_controller_cannot_take_are_refused_before_writing(make_station: Callable[..., Station],
                                                                    robot: Robot) -> None:
    old = make_station(compensation=False)
    with pytest.raises(CapabilityError, match="no compensation block"):
        old.params.upload(geometry(robot), compensation=a_block())
    assert old.params.records[-1].writes == []
    assert old.params.upload(geometry(robot)).outcome == "committed"  # a 1.0 controller still takes geometry
    blind = make_station(force_reading=False)
    with pytest.raises(CapabilityError, match="FORCE_READING"):
        blind.params.upload(geometry(robot), compensation=a_block())
    assert blind.params.upload(geometry(robot), compensation=a_block(compliance=0.0).model_copy(
        update={"compliance_mm_per_kn_m": [0.0] * 6})).outcome == "committed"


def test_invalid_blocks_never_reach_the_wire() -> None:
    fields = a_block().model_dump()
    with pytest.raises(ValueError, match="scale_ppm"):
        CompensationBlock.model_validate({**fields, "scale_ppm": [1e6, 0, 0, 0, 0, 0]})
    with pytest.raises(ValueError, match="same number of points"):
        CompensationBlock.model_validate({**fields, "table_mm": [[0.0, 0.0]] * 5 + [[0.0] * 3]})
    with pytest.raises(ValueError, match="table_end_mm"):
        CompensationBlock.model_validate({**fields, "table_end_mm": [5.0] * 6})
    with pytest.raises(ValueError):
        CompensationBlock.model_validate({**fields, "backlash_mm": [float("nan")] * 6})
    with pytest.raises(ParameterValidationError):
        CompensationBlock.from_words([0] * BLOCK_REGISTERS)  # format 0 is no block


def test_sensor_readings_are_served(make_station: Callable[..., Station]) -> None:
    st = make_station()
    forces = st.params.read_leg_forces_kn()
    np.testing.assert_allclose(forces, st.controller.leg_forces_reading(), rtol=1e-6)
    assert forces.shape == (6,) and np.all(forces > 0)  # the platform's weight compresses every leg
    temperature = st.params.read_temperature_c()
    assert 15.0 < temperature < 30.0
    old = make_station(compensation=False)
    with pytest.raises(Exception, match="exception 2"):
        old.params.read_leg_forces_kn()


def test_a_thermal_term_needs_a_temperature_reading(make_station: Callable[..., Station], robot: Robot) -> None:
    st = make_station(temperature_reading=False)
    with pytest.raises(CapabilityError, match="TEMPERATURE_READING"):
        st.params.upload(geometry(robot), compensation=a_block(thermal=11.0))
    assert st.params.records[-1].writes == [] and st.raw.block(COMP_LIVE)["points"] == 0
