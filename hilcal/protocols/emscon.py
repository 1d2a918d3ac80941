"""Leica emScon (the AT4xx tracker programming interface): packets, codes and framing, shared by the tracker driver
(``drivers.tracker.emscon``) and the simulated tracker (``sim_devices.tracker``).

The packet layouts are not written here: they come from ``CESAPI.packet`` (the MIT-licensed ``cesapi`` package,
generated from Leica's ``ES_C_API_Def.h``, the AT4xx extract of emScon TPI 3.6). This module is the only one of
ours that imports CESAPI, and it imports ``CESAPI.packet`` alone: ``CESAPI.connection`` and ``CESAPI.command`` call
``logging.basicConfig()`` at import. Each packet is a little-endian C struct (``#pragma pack(4)``) that starts with
``PacketHeaderT`` = (``lPacketSize`` int32: the whole packet's size in bytes, ``type`` uint32: ``ES_DataType``).
A command (``...CT``) carries its ``ES_Command`` code; its answer (``...RT``) the same code and an ``ES_ResultStatus``.
Results (``SingleMeasResultT``), unsolicited errors (``ErrorResponseT``) and notices (``SystemStatusChangeT``)
carry their own data type. See docs/protocols.md (Laser tracker).

The enums below are built from CESAPI's constants by prefix (``ES_C_`` -> ``Command``, ``ES_RS_`` ->
``ResultStatus``, ...), keeping Leica's names without the prefix (``Command.StartMeasurement``,
``ResultStatus.AllOK``), so a trace reads like Leica's documentation.
"""

from __future__ import annotations

import struct
from enum import IntEnum
from typing import Any

from CESAPI import packet as _cesapi

DEFAULT_PORT = 700
"""emScon's TCP port on a real tracker controller."""
HEADER = struct.Struct("<iI")
"""PacketHeaderT: lPacketSize (int32, bytes of the whole packet), type (ES_DataType)."""
HEADER_BYTES = HEADER.size
MIN_PACKET_BYTES = 12
"""The smallest packet: a header and one 32-bit field (a command without parameters, a status change)."""
MAX_PACKET_BYTES = 65536
"""A header that announces more than this (or less than ``MIN_PACKET_BYTES``) is not a packet: the stream has lost
its framing (the largest AT4xx packet is under 1 kB; the bound leaves room for data types of newer servers)."""
NAME_BYTES = 64
"""Reflector names: 32 UTF-16 code units (``unsigned short cReflectorName[32]``)."""


def _members(*prefixes: str, exclude: tuple[str, ...] = ()) -> dict[str, int]:
    """CESAPI's constants with one of the prefixes, by name without the prefix."""
    out: dict[str, int] = {}
    for name, value in vars(_cesapi).items():
        for prefix in prefixes:
            if name.startswith(prefix) and isinstance(value, int) and name[len(prefix):] not in exclude:
                out[name[len(prefix):]] = value
    return out


DataType = IntEnum("DataType", _members("ES_DT_"))  # type: ignore[misc]
Command = IntEnum("Command", _members("ES_C_"))  # type: ignore[misc]
ResultStatus = IntEnum("ResultStatus", _members("ES_RS_"))  # type: ignore[misc]
LengthUnit = IntEnum("LengthUnit", _members("ES_LU_"))  # type: ignore[misc]
AngleUnit = IntEnum("AngleUnit", _members("ES_AU_"))  # type: ignore[misc]
TemperatureUnit = IntEnum("TemperatureUnit", _members("ES_TU_"))  # type: ignore[misc]
PressureUnit = IntEnum("PressureUnit", _members("ES_PU_"))  # type: ignore[misc]
HumidityUnit = IntEnum("HumidityUnit", _members("ES_HU_"))  # type: ignore[misc]
CoordinateSystemType = IntEnum("CoordinateSystemType", _members("ES_CS_"))  # type: ignore[misc]
MeasMode = IntEnum("MeasMode", _members("ES_MM_"))  # type: ignore[misc]
TrackerStatus = IntEnum("TrackerStatus", _members("ES_TS_"))  # type: ignore[misc]
TargetType = IntEnum("TargetType", _members("ES_TT_", exclude=("Undefined", "ATC400")))  # type: ignore[misc]
"""ES_TargetType (``ES_TT_`` is also the prefix of ES_TrackerProcessorType's two values, left out)."""
SystemStatusChange = IntEnum("SystemStatusChange", _members("ES_SSC_", "ES_SCC_"))  # type: ignore[misc]
"""ES_SystemStatusChange (two of its values are spelt ``ES_SCC_`` in Leica's header)."""


def _classes(suffix: str) -> dict[int, type]:
    """CESAPI's command (``CT``) or answer (``RT``) classes by their command code."""
    out: dict[int, type] = {}
    for name, cls in vars(_cesapi).items():
        if isinstance(cls, type) and name.endswith(suffix) and name not in ("BasicCommandCT", "BasicCommandRT"):
            out[cls().packetInfo.command] = cls
    return out


COMMAND_CLASSES: dict[int, type] = _classes("CT")
"""Command code -> CESAPI class of the command packet."""
ANSWER_CLASSES: dict[int, type] = _classes("RT")
"""Command code -> CESAPI class of its answer."""

SingleMeasResultT = _cesapi.SingleMeasResultT
ErrorResponseT = _cesapi.ErrorResponseT
SystemStatusChangeT = _cesapi.SystemStatusChangeT
ReflectorPosResultT = _cesapi.ReflectorPosResultT
Packet = Any
"""A CESAPI packet object (its fields are attributes; ``pack()`` gives its bytes)."""


class PacketError(ValueError):
    """Bytes that are not an emScon packet this module knows."""


class FramingError(PacketError):
    """A header whose size cannot be a packet's: the stream is out of step and cannot be read on."""


class UnknownPacket(PacketError):
    """A well-framed packet of a data type or command code the AT4xx definitions do not know."""

    def __init__(self, message: str, data_type: int, command: int | None = None) -> None:
        super().__init__(message)
        self.data_type = data_type
        self.command = command


def name_of(enum: type[IntEnum], value: int) -> str:
    """``Name (value)`` of a code, or ``value`` alone for a code the enum does not know."""
    try:
        return f"{enum(value).name} ({value})"
    except ValueError:
        return str(value)


def new_command(command: int) -> Packet:
    """A command packet (``...CT``) with its header and command code set; the caller sets its fields."""
    return COMMAND_CLASSES[int(command)]()


def new_answer(command: int, status: int = 0) -> Packet:
    """The answer packet (``...RT``) of a command, with its status."""
    packet = ANSWER_CLASSES[int(command)]()
    packet.packetInfo.status = int(status)
    return packet


def new_error(command: int, status: int) -> Packet:
    """An ``ErrorResponseT``: an error the tracker reports outside a command's answer."""
    packet = ErrorResponseT()
    packet.command, packet.status = int(command), int(status)
    return packet


def new_status_change(change: int) -> Packet:
    """A ``SystemStatusChangeT`` notice."""
    packet = SystemStatusChangeT()
    packet.systemStatusChange = int(change)
    return packet


def encode(packet: Packet) -> bytes:
    """The packet's bytes; ValueError if its header's size is not its length (a layout error)."""
    data = packet.pack()
    size, _ = HEADER.unpack_from(data)
    if size != len(data):
        raise ValueError(f"{type(packet).__name__} packs {len(data)} bytes but its header says {size}")
    return data


def packet_type(packet: Packet) -> int:
    """The data type in a packet's header."""
    info = packet if hasattr(packet, "packetHeader") else packet.packetInfo
    return int(info.packetHeader.type)


def peek_header(buffer: bytes | bytearray) -> tuple[int, int] | None:
    """(size, data type) of the packet the buffer starts with; None before a whole header is in. FramingError for a
    size no packet has."""
    if len(buffer) < HEADER_BYTES:
        return None
    size, data_type = HEADER.unpack_from(buffer)
    if not MIN_PACKET_BYTES <= size <= MAX_PACKET_BYTES:
        raise FramingError(f"a packet header announces {size} bytes (a packet has {MIN_PACKET_BYTES} to "
                           f"{MAX_PACKET_BYTES}): {bytes(buffer[:16]).hex(' ')}")
    return size, data_type


def take_packets(buffer: bytearray) -> list[bytes]:
    """Remove the complete packets at the start of ``buffer`` and return them (a partial packet stays). FramingError
    (the buffer left as it was from the bad header on) when a header cannot be a packet's."""
    out: list[bytes] = []
    while (header := peek_header(buffer)) is not None and len(buffer) >= header[0]:
        out.append(bytes(buffer[: header[0]]))
        del buffer[: header[0]]
    return out


def decode(data: bytes, *, answer: bool) -> Packet:
    """A whole packet's bytes as a CESAPI object: answers and results (``answer=True``, the client's side) or
    commands (``answer=False``, the tracker's side). UnknownPacket for a data type or command code the AT4xx
    definitions lack; PacketError for a packet too short or too long for its layout."""
    header = peek_header(data)
    if header is None or header[0] != len(data):
        raise PacketError(f"{len(data)} bytes are not one whole packet")
    size, data_type = header
    command = struct.unpack_from("<I", data, HEADER_BYTES)[0]
    if data_type not in DataType._value2member_map_:
        raise UnknownPacket(f"unknown data type {data_type} ({size} bytes)", data_type)
    if data_type == DataType.Command and command not in (ANSWER_CLASSES if answer else COMMAND_CLASSES):
        raise UnknownPacket(f"unknown command {command} ({size} bytes)", data_type, command)
    try:
        packet = _cesapi.PacketFactory().packet(data, return_type=answer)
        expected = len(packet.pack())
    except (struct.error, AttributeError, TypeError) as err:
        raise PacketError(f"{name_of(DataType, data_type)} packet of {size} bytes does not unpack: {err}") from None
    if expected != size:
        raise PacketError(f"{type(packet).__name__} has {expected} bytes, the packet {size}")
    return packet


def encode_name(name: str) -> bytes:
    """A reflector name as emScon's 32 UTF-16 code units (truncated, zero-padded)."""
    return name.encode("utf-16-le")[: NAME_BYTES - 2].ljust(NAME_BYTES, b"\0")


def decode_name(raw: bytes) -> str:
    """A reflector name from its 32 UTF-16 code units (up to the first zero)."""
    text = raw[:NAME_BYTES].decode("utf-16-le", errors="replace")
    return text.split("\0", 1)[0]
