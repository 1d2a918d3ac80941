"""Modbus framing, server side: MBAP (TCP) and address + CRC-16 (RTU) frames, request PDUs, exception PDUs.

Function codes 3 (read holding registers), 6 (write single) and 16 (write multiple), written from the Modbus
Application Protocol v1.1b3 rather than on pymodbus' server datastore, so the driver's pymodbus client is tested
against an independent peer.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass

from hilcal.protocols.checksums import crc16_modbus
from hilcal.protocols.registers import MAX_READ_REGISTERS, MAX_WRITE_REGISTERS, ModbusExceptionCode

READ_HOLDING = 0x03
WRITE_SINGLE = 0x06
WRITE_MULTIPLE = 0x10
MBAP_BYTES = 7
MAX_PDU_BYTES = 253


class ModbusFrameError(ValueError):
    """Bytes that are not a Modbus TCP frame; the server closes the connection (no response is possible)."""


class ModbusError(Exception):
    """A request answered with a Modbus exception response."""

    def __init__(self, code: ModbusExceptionCode, message: str = "") -> None:
        super().__init__(f"{code.name}: {message}" if message else code.name)
        self.code = code


@dataclass(frozen=True)
class MbapHeader:
    transaction_id: int
    protocol_id: int
    length: int
    unit_id: int


def parse_mbap(header: bytes) -> MbapHeader:
    """Parse the 7-byte MBAP header; ``length`` counts the unit ID and the PDU (2..254)."""
    if len(header) != MBAP_BYTES:
        raise ModbusFrameError(f"MBAP header needs {MBAP_BYTES} bytes, got {len(header)}")
    tid, pid, length, unit = struct.unpack(">HHHB", header)
    if pid != 0:
        raise ModbusFrameError(f"protocol identifier {pid} is not 0 (Modbus)")
    if not 2 <= length <= MAX_PDU_BYTES + 1:
        raise ModbusFrameError(f"MBAP length {length} outside 2..{MAX_PDU_BYTES + 1}")
    return MbapHeader(tid, pid, length, unit)


@dataclass(frozen=True)
class ModbusRequest:
    function: int
    address: int
    count: int
    values: tuple[int, ...] = ()

    @property
    def is_write(self) -> bool:
        return self.function in (WRITE_SINGLE, WRITE_MULTIPLE)


def decode_request_pdu(pdu: bytes) -> ModbusRequest:
    """Decode a request PDU; ModbusError for what deserves an exception response, ModbusFrameError if empty."""
    if not pdu:
        raise ModbusFrameError("empty PDU")
    function, body = pdu[0], pdu[1:]
    if function == READ_HOLDING:
        if len(body) != 4:
            raise ModbusError(ModbusExceptionCode.ILLEGAL_DATA_VALUE, "FC3 needs address and quantity")
        address, count = struct.unpack(">HH", body)
        if not 1 <= count <= MAX_READ_REGISTERS:
            raise ModbusError(ModbusExceptionCode.ILLEGAL_DATA_VALUE, f"quantity {count} outside 1..125")
        return ModbusRequest(function, address, count)
    if function == WRITE_SINGLE:
        if len(body) != 4:
            raise ModbusError(ModbusExceptionCode.ILLEGAL_DATA_VALUE, "FC6 needs address and value")
        address, value = struct.unpack(">HH", body)
        return ModbusRequest(function, address, 1, (value,))
    if function == WRITE_MULTIPLE:
        if len(body) < 5:
            raise ModbusError(ModbusExceptionCode.ILLEGAL_DATA_VALUE, "FC16 too short")
        address, count, byte_count = struct.unpack(">HHB", body[:5])
        if not 1 <= count <= MAX_WRITE_REGISTERS or byte_count != 2 * count or len(body) != 5 + byte_count:
            raise ModbusError(ModbusExceptionCode.ILLEGAL_DATA_VALUE, "FC16 quantity/byte count mismatch")
        values = struct.unpack(f">{count}H", body[5:])
        return ModbusRequest(function, address, count, values)
    raise ModbusError(ModbusExceptionCode.ILLEGAL_FUNCTION, f"function code {function}")


def exception_pdu(function: int, code: ModbusExceptionCode) -> bytes:
    return bytes(((function | 0x80) & 0xFF, int(code)))


def rtu_request_length(buffer: bytes) -> int | None:
    """Length of the RTU request starting the buffer: an int, None if more bytes are needed, -1 if unknown."""
    if len(buffer) < 2:
        return None
    function = buffer[1]
    if function in (READ_HOLDING, WRITE_SINGLE):
        return 8
    if function == WRITE_MULTIPLE:
        return None if len(buffer) < 7 else 9 + buffer[6]
    return -1


def rtu_split(frame: bytes) -> tuple[int, bytes]:
    """(address, PDU) of an RTU frame; ModbusFrameError if too short or the CRC-16 (low byte first) is wrong."""
    if len(frame) < 4:
        raise ModbusFrameError(f"RTU frame of {len(frame)} bytes")
    if crc16_modbus(frame[:-2]) != int.from_bytes(frame[-2:], "little"):
        raise ModbusFrameError("RTU CRC-16 mismatch")
    return frame[0], frame[1:-2]


def rtu_frame(address: int, pdu: bytes) -> bytes:
    body = bytes([address]) + pdu
    return body + crc16_modbus(body).to_bytes(2, "little")
