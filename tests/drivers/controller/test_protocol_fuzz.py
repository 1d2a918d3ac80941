"""Property-based fuzzing of the controller protocol parsers: random input gives a clean typed error or a
valid result, never a crash or a hang. Covers the SLCAN line parser (server side), CAN frame decoding with
counter/checksum on both sides, the Modbus float32 register block decode and the Modbus TCP server parser.
"""

from __future__ import annotations

import socket
import struct
import time
from collections.abc import Iterator

import numpy as np
import pytest
import serial
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from drivers.controller.can_codec import FrameCodec
from drivers.controller.modbus import ParameterSet, ParameterValidationError
from hilcal.protocols.checksums import can_frame_checksum
from hilcal.protocols.registers import (
    PARAMETER_REGISTERS,
    ModbusExceptionCode,
    crc32_of_words,
    floats_from_words,
    parameter_limit_violations,
)
from hilcal.robot import Robot
from sim_devices.controller.can_peer import CanCodec, CanFrameError, ControllerCanPeer
from sim_devices.controller.modbus_faults import ModbusFaultInjector
from sim_devices.controller.modbus_frames import (
    MbapHeader,
    ModbusError,
    ModbusFrameError,
    ModbusRequest,
    decode_request_pdu,
    parse_mbap,
    rtu_frame,
    rtu_request_length,
    rtu_split,
)
from sim_devices.controller.modbus_protocol import ControllerRegisterMap, ModbusProtocol
from sim_devices.controller.modbus_server import ModbusTcpServer
from sim_devices.controller.slcan_protocol import SlcanCommand, SlcanError, SlcanLineSplitter, parse_slcan_line
from sim_devices.controller.slcan_server import SlcanServer
from sim_devices.controller.state_machine import ControllerSimConfig, SimulatedController
from sim_devices.rig.config import GeometryErrors, RigConfig
from sim_devices.rig.rig import SimulatedRig

pytestmark = pytest.mark.timeout(120)
FUZZ = settings(deadline=None, max_examples=200, suppress_health_check=[HealthCheck.function_scoped_fixture])

DRIVER_CODEC = FrameCodec()
SIM_CODEC = CanCodec()
CONTROLLER_IDS = [m.frame_id for m in DRIVER_CODEC.db.messages]


# ------------------------------------------------------------------ SLCAN


@FUZZ
@given(st.binary(max_size=80))
def test_slcan_parser_random_bytes(line: bytes) -> None:
    try:
        command = parse_slcan_line(line)
    except SlcanError:
        return
    assert isinstance(command, SlcanCommand)
    if command.frame_id is not None:
        assert len(command.data) <= 8
        assert command.frame_id <= (0x1FFFFFFF if command.extended else 0x7FF)


@FUZZ
@given(st.text(alphabet="tTrRSOCVNFZ0123456789ABCDEFabcdefxyz \x07\x00", max_size=30))
def test_slcan_parser_near_valid_text(text: str) -> None:
    try:
        parse_slcan_line(text.encode())
    except SlcanError:
        pass


@FUZZ
@given(st.integers(0, 0x7FF), st.binary(max_size=8), st.booleans())
def test_slcan_valid_frame_lines_parse_exactly(frame_id: int, data: bytes, lower: bool) -> None:
    payload = data.hex() if lower else data.hex().upper()
    command = parse_slcan_line(f"t{frame_id:03X}{len(data)}{payload}".encode())
    assert (command.code, command.frame_id, command.data, command.extended) == ("t", frame_id, data, False)


@FUZZ
@given(st.lists(st.binary(max_size=40), max_size=20))
def test_slcan_line_splitter_random_chunks(chunks: list[bytes]) -> None:
    splitter = SlcanLineSplitter(max_line_bytes=64)
    for chunk in chunks:
        for item in splitter.feed(chunk):
            if isinstance(item, bytes):
                assert b"\r" not in item and len(item) <= 64
            else:
                assert isinstance(item, SlcanError)


# ------------------------------------------------------------------ CAN frames with counter and checksum


@FUZZ
@given(st.integers(0, 0x7FF), st.binary(max_size=8))
def test_can_decode_random_frames(frame_id: int, data: bytes) -> None:
    for decode, error in ((DRIVER_CODEC.decode, Exception), (SIM_CODEC.decode, CanFrameError)):
        try:
            decode(frame_id, data)
        except error as err:
            if decode is DRIVER_CODEC.decode:
                assert type(err).__name__ in {"UnknownFrame", "FrameLengthError", "ChecksumError", "FrameError"}


@FUZZ
@given(st.sampled_from(CONTROLLER_IDS), st.binary(min_size=7, max_size=7))
def test_can_decode_random_payload_with_valid_checksum(frame_id: int, payload: bytes) -> None:
    data = payload + bytes([can_frame_checksum(frame_id, payload)])
    decoded = DRIVER_CODEC.decode(frame_id, data)
    name, signals = SIM_CODEC.decode(frame_id, data)
    assert decoded.name == name and decoded.signals == signals
    assert decoded.counter == payload[6] & 0x0F


@FUZZ
@given(
    st.sampled_from(["SetpointL12", "SetpointL34", "SetpointL56"]),
    st.integers(0, (1 << 24) - 1),
    st.integers(0, (1 << 24) - 1),
    st.integers(0, 15),
    st.integers(0, 63),
)
def test_can_sealed_frames_round_trip_and_detect_single_bit_errors(
    name: str, first_um: int, second_um: int, counter: int, bit: int
) -> None:
    a = int(name[-2])
    signals = {f"Leg{a}Setpoint": first_um, f"Leg{a + 1}Setpoint": second_um}
    msg = DRIVER_CODEC.encode(name, signals, counter)
    decoded_name, decoded = SIM_CODEC.decode(msg.arbitration_id, bytes(msg.data))
    assert decoded_name == name and decoded["Counter"] == counter
    assert decoded[f"Leg{a}Setpoint"] == first_um and decoded[f"Leg{a + 1}Setpoint"] == second_um
    flipped = bytearray(msg.data)
    flipped[bit // 8] ^= 1 << (bit % 8)
    with pytest.raises(CanFrameError, match="checksum"):
        SIM_CODEC.decode(msg.arbitration_id, bytes(flipped))


# ------------------------------------------------------------------ Modbus register blocks


@FUZZ
@given(st.lists(st.integers(0, 0xFFFF), min_size=PARAMETER_REGISTERS, max_size=PARAMETER_REGISTERS))
def test_parameter_block_decode_random_words(words: list[int]) -> None:
    try:
        params = ParameterSet.from_words(words)
    except ParameterValidationError:
        values = floats_from_words(words)
        assert parameter_limit_violations(values)
        return
    assert np.isfinite(params.to_vector()).all()
    assert params.to_words() == words


@FUZZ
@given(st.lists(st.integers(-5, 0x1FFFF), max_size=100))
def test_parameter_block_decode_wrong_shapes(words: list[int]) -> None:
    try:
        ParameterSet.from_words(words)
    except ParameterValidationError:
        return
    assert len(words) == PARAMETER_REGISTERS


# ------------------------------------------------------------------ Modbus TCP server parser


@pytest.fixture(scope="module")
def controller() -> SimulatedController:
    from hilcal.robot import default_robot

    robot: Robot = default_robot()
    rig = SimulatedRig(robot, RigConfig(seed=5, errors=GeometryErrors.zero()))
    return SimulatedController(robot, rig, ControllerSimConfig())


@FUZZ
@given(st.binary(max_size=12))
def test_mbap_header_random_bytes(data: bytes) -> None:
    try:
        header = parse_mbap(data)
    except ModbusFrameError:
        return
    assert isinstance(header, MbapHeader) and header.protocol_id == 0 and 2 <= header.length <= 254


@FUZZ
@given(st.binary(max_size=260))
def test_request_pdu_random_bytes(pdu: bytes) -> None:
    try:
        request = decode_request_pdu(pdu)
    except (ModbusError, ModbusFrameError):
        return
    assert isinstance(request, ModbusRequest) and 1 <= request.count <= 125


@FUZZ
@given(data=st.binary(max_size=300))
def test_protocol_handles_random_adus(controller: SimulatedController, data: bytes) -> None:
    protocol = ModbusProtocol(ControllerRegisterMap(controller), 1, ModbusFaultInjector())
    try:
        response = protocol.handle_adu(data)
    except ModbusFrameError:
        return
    assert response is not None
    header = parse_mbap(response[:7])
    assert header.length == len(response) - 6
    if response[7] & 0x80:  # an exception response; device failure would mean the handler crashed
        assert response[8] in (
            ModbusExceptionCode.ILLEGAL_FUNCTION,
            ModbusExceptionCode.ILLEGAL_DATA_ADDRESS,
            ModbusExceptionCode.ILLEGAL_DATA_VALUE,
            ModbusExceptionCode.GATEWAY_TARGET_FAILED,
        )


@FUZZ
@given(st.integers(0, 0xFFFF), st.sampled_from([0, 1, 0xFF, 7]), st.binary(min_size=1, max_size=253))
def test_protocol_handles_random_pdus_in_valid_frames(
    controller: SimulatedController, tid: int, unit: int, pdu: bytes
) -> None:
    protocol = ModbusProtocol(ControllerRegisterMap(controller), 1, ModbusFaultInjector())
    response = protocol.handle_adu(struct.pack(">HHHB", tid, 0, len(pdu) + 1, unit) + pdu)
    assert response is not None
    header = parse_mbap(response[:7])
    assert (header.transaction_id, header.unit_id, header.length) == (tid, unit, len(response) - 6)
    function = response[7]
    assert function & 0x7F == pdu[0] & 0x7F
    if function & 0x80:
        expected = ModbusExceptionCode.GATEWAY_TARGET_FAILED if unit == 7 else None
        assert response[8] != ModbusExceptionCode.SERVER_DEVICE_FAILURE
        assert expected is None or response[8] == expected
    else:
        assert unit != 7 and function in (3, 6, 16)


@FUZZ
@given(st.binary(max_size=40))
def test_rtu_framing_random_bytes(data: bytes) -> None:
    length = rtu_request_length(data)
    assert length is None or length == -1 or 8 <= length <= 9 + 255
    try:
        address, pdu = rtu_split(data)
    except ModbusFrameError:
        return
    assert rtu_frame(address, pdu) == data


write_request = st.one_of(
    st.tuples(st.just(6), st.integers(0, 0x0500), st.lists(st.integers(0, 0xFFFF), min_size=1, max_size=1)),
    st.tuples(st.just(16), st.integers(0, 0x0500), st.lists(st.integers(0, 0xFFFF), min_size=1, max_size=90)),
    st.tuples(st.just(16), st.sampled_from([0x0020, 0x0030, 0x0200, 0x0248]),
              st.lists(st.integers(0, 4), min_size=1, max_size=3)),
)


@FUZZ
@given(st.lists(write_request, max_size=25))
def test_random_writes_never_corrupt_the_live_set(requests: list[tuple[int, int, list[int]]]) -> None:
    from hilcal.robot import default_robot

    robot = default_robot()
    controller = SimulatedController(robot, SimulatedRig(robot, RigConfig(seed=1, errors=GeometryErrors.zero())))
    protocol = ModbusProtocol(ControllerRegisterMap(controller), 1, ModbusFaultInjector())
    for function, address, values in requests:
        if function == 6:
            pdu = struct.pack(">BHH", 6, address, values[0])
        else:
            pdu = struct.pack(f">BHHB{len(values)}H", 16, address, len(values), 2 * len(values), *values)
        response = protocol.handle_pdu(pdu)
        assert response is not None
        if response[0] & 0x80:
            assert response[1] in (ModbusExceptionCode.ILLEGAL_DATA_ADDRESS, ModbusExceptionCode.ILLEGAL_DATA_VALUE)
    live = controller.bank_words("live")
    assert not parameter_limit_violations(floats_from_words(live))
    assert controller.bank_crc32("live") == crc32_of_words(live)


@pytest.fixture(scope="module")
def tcp_server(controller: SimulatedController) -> Iterator[ModbusTcpServer]:
    with ModbusTcpServer(controller).start() as server:
        yield server


def _valid_read(port: int) -> bytes:
    with socket.create_connection(("127.0.0.1", port), timeout=1.0) as sock:
        sock.sendall(struct.pack(">HHHBBHH", 7, 0, 6, 1, 3, 0, 1))
        return sock.recv(64)


@settings(deadline=None, max_examples=60, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(st.binary(min_size=1, max_size=300))
def test_tcp_server_survives_random_bytes(tcp_server: ModbusTcpServer, garbage: bytes) -> None:
    with socket.create_connection(("127.0.0.1", tcp_server.port), timeout=1.0) as sock:
        sock.sendall(garbage)
        sock.settimeout(0.02)
        deadline = time.monotonic() + 0.05
        while time.monotonic() < deadline:
            try:
                if not sock.recv(512):
                    break
            except (TimeoutError, ConnectionResetError):
                break
    assert _valid_read(tcp_server.port) == struct.pack(">HHHBBBH", 7, 0, 5, 1, 3, 2, 0x4843)


@pytest.fixture(scope="module")
def slcan_port(controller: SimulatedController) -> Iterator[serial.Serial]:
    with SlcanServer(ControllerCanPeer(controller)).start() as server:
        port = serial.Serial(server.channel, timeout=0.5)
        try:
            yield port
        finally:
            port.close()


@settings(deadline=None, max_examples=50, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(st.binary(max_size=200))
def test_slcan_server_survives_random_bytes(slcan_port: serial.Serial, garbage: bytes) -> None:
    slcan_port.write(garbage + b"\r")
    slcan_port.write(b"V\r")
    reply = slcan_port.read_until(b"V1013\r")
    assert reply.endswith(b"V1013\r")
    slcan_port.write(b"C\r")
    time.sleep(0.005)
    slcan_port.reset_input_buffer()
