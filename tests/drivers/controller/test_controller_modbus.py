"""Controller parameters over Modbus TCP: the real pymodbus-based driver against the simulated controller.

Register contents are checked with a plain pymodbus client and ``struct`` (float32 ABCD as documented), and
CRC-32 with ``zlib``, independently of the driver's own encoding.
"""

from __future__ import annotations

import hashlib
import struct
import zlib
from collections.abc import Callable, Iterator
from contextlib import ExitStack
from dataclasses import dataclass

import numpy as np
import pytest
import serial
from pymodbus.client import ModbusTcpClient

from drivers.controller.modbus import (
    CapabilityError,
    ControllerParams,
    ModbusExceptionResponse,
    ModbusTransportError,
    NotDisabled,
    ParameterSet,
    ParameterValidationError,
    ReadbackMismatch,
    UploadRefused,
)
from hilcal.protocols.checksums import crc16_modbus
from hilcal.protocols.controller_states import Command, ControllerState, FaultCode
from hilcal.protocols.registers import ModbusExceptionCode, ParamStatus
from hilcal.robot import Robot
from sim_devices.controller.modbus_server import ModbusRtuServer, ModbusTcpServer
from sim_devices.controller.state_machine import ControllerSimConfig, SimulatedController
from sim_devices.rig.config import GeometryErrors, RigConfig
from sim_devices.rig.rig import SimulatedRig

pytestmark = pytest.mark.timeout(60)

# addresses from the register map table in docs/protocols.md
MAGIC, CAPABILITIES, STATE = 0x0000, 0x0005, 0x0010
PARAM_COMMAND, PARAM_STATUS, SAVE_COUNTER, STAGED_WRITTEN = 0x0020, 0x0021, 0x0023, 0x0024
LIVE_CRC32, STAGED_LENGTH = 0x0028, 0x0030
LIVE, STAGING, BACKUP, SAVED = 0x0100, 0x0200, 0x0300, 0x0400
OPEN_STAGING, COMMIT, ROLLBACK, SAVE = 1, 2, 3, 4


def f32(values: np.ndarray) -> np.ndarray:
    return np.asarray(values, dtype=np.float32).astype(float)


def to_words(values: np.ndarray) -> list[int]:
    return list(struct.unpack(">84H", struct.pack(">42f", *values)))


def crc32(values: np.ndarray) -> int:
    return zlib.crc32(struct.pack(">42f", *values))


def nominal(robot: Robot) -> np.ndarray:
    return np.concatenate([robot.a.ravel(), robot.b.ravel(), robot.l0])


class Raw:
    """A plain pymodbus client for independent register checks."""

    def __init__(self, port: int) -> None:
        self.client = ModbusTcpClient("127.0.0.1", port=port, timeout=1.0, retries=0)

    def read(self, address: int, count: int) -> list[int]:
        response = self.client.read_holding_registers(address, count=count, device_id=1)
        assert not response.isError(), response
        return list(response.registers)

    def read_set(self, address: int) -> np.ndarray:
        return np.array(struct.unpack(">42f", struct.pack(">84H", *self.read(address, 84))), dtype=float)

    def write(self, address: int, values: list[int]) -> int | None:
        """Write; returns the Modbus exception code or None."""
        if len(values) == 1:
            response = self.client.write_register(address, values[0], device_id=1)
        else:
            response = self.client.write_registers(address, values, device_id=1)
        return response.exception_code if response.isError() else None


@dataclass
class MbRig:
    controller: SimulatedController
    server: ModbusTcpServer
    params: ControllerParams
    raw: Raw


@pytest.fixture
def rig(robot: Robot) -> SimulatedRig:
    return SimulatedRig(robot, RigConfig(seed=11, errors=GeometryErrors.zero()))


@pytest.fixture
def make_mb(robot: Robot, rig: SimulatedRig) -> Iterator[Callable[..., MbRig]]:
    stack = ExitStack()

    def make(**config: object) -> MbRig:
        controller = SimulatedController(robot, rig, ControllerSimConfig(**config))
        server = ModbusTcpServer(controller).start()
        stack.callback(server.close)
        params = ControllerParams("127.0.0.1", server.port, device_id=1, timeout_s=1.0)
        stack.callback(params.close)
        raw = Raw(server.port)
        stack.callback(raw.client.close)
        return MbRig(controller, server, params, raw)

    yield make
    stack.close()


@pytest.fixture
def mb(make_mb: Callable[..., MbRig]) -> MbRig:
    return make_mb()


@pytest.fixture
def new_set(robot: Robot) -> np.ndarray:
    rng = np.random.default_rng(2024)
    return nominal(robot) + rng.normal(0.0, 0.5, 42)


# ------------------------------------------------------------------ identity and encoding


def test_identity_and_capabilities(make_mb: Callable[..., MbRig]) -> None:
    full = make_mb(serial_number=0x12345678, firmware_version=0x0203)
    identity = full.params.read_identity()
    assert (identity.magic, identity.protocol_version, identity.firmware_version) == (0x4843, 0x0101, 0x0203)
    assert identity.serial_number == 0x12345678 and identity.parameter_count == 42
    assert int(identity.capabilities) == 0x1 | 0x4 | 0x8 | 0x10 | 0x20 | 0x40 and not identity.offsets_only
    assert identity.compensation
    assert full.raw.read(0x0003, 2) == [0x1234, 0x5678]
    limited = make_mb(capabilities="offsets_only", compensation=False)
    assert limited.raw.read(CAPABILITIES, 1) == [0x2 | 0x4 | 0x8]
    assert limited.raw.read(0x0001, 1) == [0x0100]
    assert limited.params.read_identity().offsets_only and not limited.params.read_identity().compensation
    bare = make_mb(force_reading=False, temperature_reading=False)
    assert bare.raw.read(CAPABILITIES, 1) == [0x1 | 0x4 | 0x8 | 0x10]


def test_live_set_is_float32_abcd_in_documented_order(mb: MbRig, robot: Robot) -> None:
    expected = f32(nominal(robot))
    raw = mb.raw.read_set(LIVE)
    np.testing.assert_array_equal(raw, expected)
    assert raw[0] == np.float32(robot.a[0, 0]) and raw[18 + 4] == np.float32(robot.b[1, 1])
    assert raw[41] == np.float32(robot.l0[5])
    np.testing.assert_array_equal(mb.params.read_live().to_vector(), expected)
    assert mb.raw.read(LIVE_CRC32, 2) == [crc32(expected) >> 16, crc32(expected) & 0xFFFF]


# ------------------------------------------------------------------ the upload transaction


def test_upload_commits_with_read_back_and_record(mb: MbRig, robot: Robot, new_set: np.ndarray) -> None:
    old = f32(nominal(robot))
    record = mb.params.upload(new_set)
    new = f32(new_set)
    np.testing.assert_array_equal(mb.raw.read_set(LIVE), new)
    np.testing.assert_array_equal(mb.raw.read_set(BACKUP), old)
    np.testing.assert_array_equal(mb.raw.read_set(SAVED), old)  # saving is a separate step
    np.testing.assert_array_equal(mb.controller.live_parameters(), new)
    assert mb.raw.read(LIVE_CRC32, 2) == [crc32(new) >> 16, crc32(new) & 0xFFFF]
    assert record.outcome == "committed" and record.error is None
    assert record.staging_readback_match and record.live_readback_match and not record.saved
    assert record.params_crc32 == f"{crc32(new):08x}"
    assert record.params_sha256 == hashlib.sha256(struct.pack(">42f", *new)).hexdigest()
    assert record.previous_live_sha256 == hashlib.sha256(struct.pack(">42f", *old)).hexdigest()
    assert record.live_after_sha256 == record.params_sha256
    assert record.started_at <= record.finished_at
    assert record.writes and all(w.ok for w in record.writes)
    assert all(w.count <= 123 for w in record.writes)
    staged = [w for w in record.writes if STAGING <= w.address < STAGING + 84]
    assert sum(w.count for w in staged) == 84 and len(staged) >= 2
    assert [(w.function, w.address) for w in mb.server.writes] == [
        ({"write_register": 6, "write_registers": 16}[w.function], w.address) for w in record.writes
    ]
    assert mb.params.records[-1] is record
    assert '"outcome":"committed"' in record.model_dump_json()


def test_rollback_restores_the_previous_set(mb: MbRig, robot: Robot, new_set: np.ndarray) -> None:
    old = f32(nominal(robot))
    mb.params.upload(new_set)
    record = mb.params.rollback()
    assert record.outcome == "rolled_back" and record.live_readback_match
    np.testing.assert_array_equal(mb.raw.read_set(LIVE), old)
    np.testing.assert_array_equal(mb.raw.read_set(BACKUP), f32(new_set))
    np.testing.assert_array_equal(mb.params.read_backup().to_vector(), f32(new_set))


def test_rollback_without_backup_is_refused(mb: MbRig, robot: Robot) -> None:
    with pytest.raises(UploadRefused) as info:
        mb.params.rollback()
    assert info.value.status is ParamStatus.NO_BACKUP
    assert info.value.record is not None and info.value.record.outcome == "refused"
    np.testing.assert_array_equal(mb.raw.read_set(LIVE), f32(nominal(robot)))


def test_save_is_a_separate_explicit_step(mb: MbRig, robot: Robot, new_set: np.ndarray) -> None:
    mb.params.upload(new_set)
    np.testing.assert_array_equal(mb.raw.read_set(SAVED), f32(nominal(robot)))
    record = mb.params.save()
    assert record.outcome == "saved" and record.saved and record.saved_readback_match
    np.testing.assert_array_equal(mb.raw.read_set(SAVED), f32(new_set))
    assert mb.raw.read(SAVE_COUNTER, 1) == [1]
    second = new_set + 0.25
    record = mb.params.upload(second, save=True)
    assert record.saved and record.outcome == "committed"
    np.testing.assert_array_equal(mb.raw.read_set(SAVED), f32(second))
    assert mb.raw.read(SAVE_COUNTER, 1) == [2]


@pytest.mark.parametrize("how", ["enabled", "fault"])
def test_upload_refused_unless_disabled_and_nothing_written(
    mb: MbRig, robot: Robot, new_set: np.ndarray, how: str
) -> None:
    if how == "enabled":
        mb.controller.command(Command.ENABLE)
    else:
        mb.controller.inject_fault(FaultCode.ENCODER)
    with pytest.raises(NotDisabled, match="ENABLED" if how == "enabled" else "FAULT") as info:
        mb.params.upload(new_set)
    assert mb.server.writes == []
    assert info.value.record is not None and info.value.record.outcome == "refused"
    assert info.value.record.writes == []
    np.testing.assert_array_equal(mb.raw.read_set(LIVE), f32(nominal(robot)))
    with pytest.raises(NotDisabled):
        mb.params.save()
    with pytest.raises(NotDisabled):
        mb.params.rollback()
    assert mb.server.writes == []


def _stage_by_hand(raw: Raw, values: np.ndarray, *, length: int = 84, crc: int | None = None,
                   registers: int = 84) -> None:
    words = to_words(values)
    assert raw.write(PARAM_COMMAND, [OPEN_STAGING]) is None
    for start in range(0, registers, 60):
        assert raw.write(STAGING + start, words[start:min(registers, start + 60)]) is None
    crc = crc32(values) if crc is None else crc
    assert raw.write(STAGED_LENGTH, [length, crc >> 16, crc & 0xFFFF]) is None


def test_controller_refuses_commit_while_enabled(mb: MbRig, robot: Robot, new_set: np.ndarray) -> None:
    _stage_by_hand(mb.raw, f32(new_set))
    mb.controller.command(Command.ENABLE)
    assert mb.raw.write(PARAM_COMMAND, [COMMIT]) is None
    assert mb.raw.read(PARAM_STATUS, 1) == [ParamStatus.NOT_DISABLED]
    np.testing.assert_array_equal(mb.raw.read_set(LIVE), f32(nominal(robot)))


@pytest.mark.parametrize(
    ("case", "status"),
    [
        ("bad_crc", ParamStatus.CRC_MISMATCH),
        ("incomplete", ParamStatus.INCOMPLETE_STAGING),
        ("wrong_length", ParamStatus.LENGTH_MISMATCH),
        ("negative_l0", ParamStatus.LIMIT_VIOLATION),
        ("huge_a", ParamStatus.LIMIT_VIOLATION),
        ("nan", ParamStatus.NOT_FINITE),
    ],
)
def test_controller_refuses_bad_staging_and_keeps_live(
    mb: MbRig, robot: Robot, new_set: np.ndarray, case: str, status: ParamStatus
) -> None:
    values = f32(new_set)
    kwargs: dict[str, int] = {}
    if case == "bad_crc":
        kwargs["crc"] = crc32(values) ^ 0x1
    elif case == "incomplete":
        kwargs.update(registers=60, length=60)
    elif case == "wrong_length":
        kwargs["length"] = 80
    elif case == "negative_l0":
        values[38] = -5.0
    elif case == "huge_a":
        values[4] = 12_000.0
    else:
        values[20] = np.nan
    _stage_by_hand(mb.raw, values, **kwargs)
    assert mb.raw.write(PARAM_COMMAND, [COMMIT]) is None
    assert mb.raw.read(PARAM_STATUS, 1) == [status]
    np.testing.assert_array_equal(mb.raw.read_set(LIVE), f32(nominal(robot)))
    assert mb.raw.read(BACKUP, 84) == [0] * 84


def test_staging_read_back_mismatch_is_not_committed(mb: MbRig, robot: Robot, new_set: np.ndarray) -> None:
    mb.server.faults.corrupt_next_write(1)
    with pytest.raises(ReadbackMismatch, match="staging") as info:
        mb.params.upload(new_set)
    assert info.value.record is not None and info.value.record.staging_readback_match is False
    assert not any(w.address == PARAM_COMMAND and w is not info.value.record.writes[0]
                   for w in info.value.record.writes)
    np.testing.assert_array_equal(mb.raw.read_set(LIVE), f32(nominal(robot)))


# ------------------------------------------------------------------ transport faults


def test_disconnect_anywhere_in_an_upload_never_mixes_sets(mb: MbRig, robot: Robot, new_set: np.ndarray) -> None:
    old = f32(nominal(robot))
    new = f32(new_set)
    writes_per_upload = len(mb.params.upload(new_set).writes)
    mb.params.rollback()
    assert writes_per_upload == 5  # OPEN, 2 staging chunks, length + CRC, COMMIT
    for n in range(1, writes_per_upload + 1):
        for execute in (False, True):
            live_before = mb.raw.read_set(LIVE)
            np.testing.assert_array_equal(live_before, old)
            mb.server.faults.drop_connection_at_write(n, execute=execute)
            with pytest.raises(ModbusTransportError) as info:
                mb.params.upload(new_set)
            record = info.value.record
            assert record is not None and record.outcome == "failed"
            assert len(record.writes) == n and not record.writes[-1].ok and record.writes[-1].error
            live = mb.raw.read_set(LIVE)
            committed = n == writes_per_upload and execute
            np.testing.assert_array_equal(live, new if committed else old, err_msg=f"n={n} execute={execute}")
            if committed:
                mb.params.rollback()
    record = mb.params.upload(new_set)
    assert record.outcome == "committed"
    np.testing.assert_array_equal(mb.raw.read_set(LIVE), new)


def test_exception_responses_are_reported_and_live_untouched(
    mb: MbRig, robot: Robot, new_set: np.ndarray
) -> None:
    old = f32(nominal(robot))
    mb.server.faults.exception_next(ModbusExceptionCode.SERVER_DEVICE_BUSY, function=6, address=PARAM_COMMAND,
                                    skip=1)
    with pytest.raises(ModbusExceptionResponse) as info:
        mb.params.upload(new_set)
    assert (info.value.code, info.value.function, info.value.address) == (6, 6, PARAM_COMMAND)
    assert info.value.record is not None and info.value.record.writes[-1].error
    np.testing.assert_array_equal(mb.raw.read_set(LIVE), old)
    mb.server.faults.exception_next(ModbusExceptionCode.SERVER_DEVICE_FAILURE, function=3, address=LIVE)
    with pytest.raises(ModbusExceptionResponse) as info:
        mb.params.read_live()
    assert info.value.code == 4
    mb.server.faults.exception_always(ModbusExceptionCode.SERVER_DEVICE_BUSY)
    with pytest.raises(ModbusExceptionResponse):
        mb.params.read_identity()
    mb.server.faults.exception_always(None)
    assert mb.params.upload(new_set).outcome == "committed"


def test_server_exception_codes_for_bad_requests(mb: MbRig) -> None:
    response = mb.raw.client.read_input_registers(0, count=1, device_id=1)
    assert response.isError() and response.exception_code == ModbusExceptionCode.ILLEGAL_FUNCTION
    response = mb.raw.client.read_holding_registers(0x0050, count=2, device_id=1)
    assert response.isError() and response.exception_code == ModbusExceptionCode.ILLEGAL_DATA_ADDRESS
    response = mb.raw.client.read_holding_registers(LIVE + 80, count=8, device_id=1)  # runs past the bank
    assert response.isError() and response.exception_code == ModbusExceptionCode.ILLEGAL_DATA_ADDRESS
    assert mb.raw.write(LIVE, [1, 2]) == ModbusExceptionCode.ILLEGAL_DATA_ADDRESS
    assert mb.raw.write(MAGIC, [7]) == ModbusExceptionCode.ILLEGAL_DATA_ADDRESS
    assert mb.raw.write(PARAM_COMMAND, [99]) == ModbusExceptionCode.ILLEGAL_DATA_VALUE
    assert mb.raw.read(STATE, 1) == [ControllerState.DISABLED]


def test_server_answers_after_a_client_disconnect(mb: MbRig) -> None:
    assert mb.raw.read(MAGIC, 1) == [0x4843]
    mb.server.disconnect_clients()
    assert mb.params.read_identity().magic == 0x4843


# ------------------------------------------------------------------ capabilities and validation


def test_offsets_only_controller(make_mb: Callable[..., MbRig], robot: Robot) -> None:
    r = make_mb(capabilities="offsets_only")
    old = f32(nominal(robot))
    changed_a = old.copy()
    changed_a[0] += 0.1
    with pytest.raises(CapabilityError, match="offsets"):
        r.params.upload(changed_a)
    assert r.server.writes == []
    new = old.copy()
    new[36:] += np.array([0.5, -0.5, 0.25, -0.25, 1.0, -1.0])
    record = r.params.upload(new)
    assert record.outcome == "committed" and record.offsets_only and record.staged_registers == 12
    staging_writes = [w for w in r.server.writes if STAGING <= w.address < STAGING + 84]
    assert staging_writes and all(w.address >= STAGING + 72 for w in staging_writes)
    np.testing.assert_array_equal(r.raw.read_set(LIVE), f32(new))
    assert r.raw.write(STAGING, [0, 0]) == ModbusExceptionCode.ILLEGAL_DATA_ADDRESS


@pytest.mark.parametrize(
    "mutate",
    [
        lambda v: v.__setitem__(3, np.nan),
        lambda v: v.__setitem__(40, -3800.0),
        lambda v: v.__setitem__(40, 0.0),
        lambda v: v.__setitem__(7, 10_500.0),
        lambda v: v.__setitem__(25, -np.inf),
    ],
)
def test_invalid_parameter_sets_are_rejected_before_any_request(
    mb: MbRig, robot: Robot, mutate: Callable[[np.ndarray], None]
) -> None:
    values = nominal(robot).copy()
    mutate(values)
    with pytest.raises(ParameterValidationError):
        mb.params.upload(values)
    with pytest.raises(ParameterValidationError, match="42"):
        mb.params.upload(nominal(robot)[:41])
    assert mb.server.protocol.requests == 0


def test_parameter_set_from_robot_round_trips_through_words(robot: Robot) -> None:
    params = ParameterSet.from_robot(robot)
    words = params.to_words()
    assert words == to_words(nominal(robot))
    np.testing.assert_array_equal(ParameterSet.from_words(words).to_vector(), f32(nominal(robot)))
    assert params.crc32() == crc32(nominal(robot))


# ------------------------------------------------------------------ Modbus RTU on a pty


@pytest.fixture
def rtu(robot: Robot, rig: SimulatedRig) -> Iterator[tuple[ModbusRtuServer, SimulatedController]]:
    controller = SimulatedController(robot, rig, ControllerSimConfig())
    with ModbusRtuServer(controller).start() as server:
        yield server, controller


def test_upload_over_modbus_rtu(
    rtu: tuple[ModbusRtuServer, SimulatedController], robot: Robot, new_set: np.ndarray
) -> None:
    server, controller = rtu
    with ControllerParams(serial_port=server.path, baudrate=115200, device_id=1, timeout_s=0.5) as params:
        assert params.read_identity().magic == 0x4843
        record = params.upload(new_set)
        assert record.outcome == "committed" and record.endpoint.startswith("rtu://")
        np.testing.assert_array_equal(controller.live_parameters(), f32(new_set))
        server.faults.drop_connection_at_write(3)
        with pytest.raises(ModbusTransportError):
            params.upload(nominal(robot))
        np.testing.assert_array_equal(params.read_live().to_vector(), f32(new_set))


def test_rtu_frames_by_hand(rtu: tuple[ModbusRtuServer, SimulatedController]) -> None:
    server, _ = rtu
    request = bytes([1, 3, 0, 0, 0, 1])
    port = serial.Serial(server.path, timeout=0.3)
    try:
        port.write(request + crc16_modbus(request).to_bytes(2, "little"))
        reply = port.read(7)
        assert reply[:5] == bytes([1, 3, 2, 0x48, 0x43])
        assert int.from_bytes(reply[5:], "little") == crc16_modbus(reply[:5])
        port.write(request + bytes([0, 0]))  # bad CRC: no answer on a serial line
        assert port.read(7) == b""
        other = bytes([9, 3, 0, 0, 0, 1])  # another device address
        port.write(other + crc16_modbus(other).to_bytes(2, "little"))
        assert port.read(7) == b""
    finally:
        port.close()
    assert server.crc_errors == 1
