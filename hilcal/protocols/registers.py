"""The controller's Modbus parameter interface, what stays code: the set's shape and bounds, the capability bits,
command and status codes, Modbus limits and the float32 ABCD word helpers of hilcal's own register map.

Where each register lives is data: the map files of ``hilcal.protocols.modbus_map`` (hilcal's own register map 1.1
is ``modbus_maps/hilcal-1.1.toml``). In that map a parameter set is 42 IEEE-754 float32 values in mm, each in two
registers, high word first and each word big-endian ("ABCD"). Order: a (leg 1 x, y, z, leg 2 x, y, z ... leg 6 z),
b (same), l0 (legs 1..6). CRC-32 (``hilcal.protocols.checksums.crc32_ieee``) is taken over the 168 bytes of the 84
registers, each register high byte first. See docs/protocols.md for the upload transaction. Register-map version 1.1
adds the COMPENSATION capability: a compensation block (``hilcal.protocols.compensation``) with its own four banks in
the same transaction as the geometry, and the controller's own leg-force and leg-temperature readings.
"""

from __future__ import annotations

import math
import struct
from collections.abc import Sequence
from enum import IntEnum, IntFlag

from hilcal.protocols.checksums import crc32_ieee

N_LEGS = 6
PARAMETER_COUNT = 42
REGISTERS_PER_FLOAT = 2
PARAMETER_REGISTERS = PARAMETER_COUNT * REGISTERS_PER_FLOAT
WORD_ORDER = "ABCD"
"""float32 byte order on the wire of hilcal's own map: high word first, each word big-endian."""

MAX_READ_REGISTERS = 125
"""Most registers one FC 3 request may read (MODBUS Application Protocol v1.1b3, 6.3: quantity 1 to 125)."""
MAX_WRITE_REGISTERS = 123
"""Most registers one FC 16 request may write (MODBUS Application Protocol v1.1b3, 6.12: quantity 1 to 123)."""
A_INDEX = 0
B_INDEX = 18
L0_INDEX = 36
L0_REGISTERS = N_LEGS * REGISTERS_PER_FLOAT

MAGIC = 0x4843
"""Value of the MAGIC register ("HC"): identifies a hilcal-compatible controller."""
PROTOCOL_VERSION = 0x0101
"""Register-map version 1.1 (major << 8 | minor): 1.0 plus the compensation block and the sensor readings."""
PROTOCOL_VERSION_1_0 = 0x0100
"""What a controller without the compensation block reports."""

PARAMETER_NAMES: tuple[str, ...] = (
    *(f"a{leg}_{axis}_mm" for leg in range(1, N_LEGS + 1) for axis in "xyz"),
    *(f"b{leg}_{axis}_mm" for leg in range(1, N_LEGS + 1) for axis in "xyz"),
    *(f"l0_{leg}_mm" for leg in range(1, N_LEGS + 1)),
)

A_B_LIMIT_MM = 10_000.0
"""|a|, |b| coordinates must not exceed this (a large hydraulic platform is a few metres across)."""
L0_MIN_MM = 1.0
L0_MAX_MM = 20_000.0
"""Leg offsets (stroke-zero lengths) must lie in [L0_MIN_MM, L0_MAX_MM]."""


class Capability(IntFlag):
    """CAPABILITIES register bits."""

    FULL_GEOMETRY = 0x0001
    """All 42 parameters (a, b, l0) are writable."""
    OFFSETS_ONLY = 0x0002
    """Only the six leg offsets l0 are writable; staging a/b registers refuse writes."""
    NONVOLATILE_SAVE = 0x0004
    ROLLBACK = 0x0008
    COMPENSATION = 0x0010
    """Register-map 1.1: the compensation block is writable in the geometry's transaction."""
    FORCE_READING = 0x0020
    """The controller reads each leg's axial force (LEG_FORCES), so compliance terms can be applied."""
    TEMPERATURE_READING = 0x0040
    """The controller reads the leg temperature (LEG_TEMPERATURE), so a thermal coefficient can be applied."""


class ParamCommand(IntEnum):
    """Values written to PARAM_COMMAND."""

    OPEN_STAGING = 1
    """Copy live into staging (geometry and block), forget what was written, clear STAGED_LENGTH and the CRCs."""
    COMMIT = 2
    """Check the staged set and swap it in atomically; the previous live set becomes the backup."""
    ROLLBACK = 3
    """Swap live and backup."""
    SAVE = 4
    """Copy live to non-volatile memory."""


class ParamStatus(IntEnum):
    """PARAM_STATUS values: the outcome of the last parameter command."""

    OK = 0
    NOT_DISABLED = 1
    INCOMPLETE_STAGING = 2
    LENGTH_MISMATCH = 3
    CRC_MISMATCH = 4
    NOT_FINITE = 5
    LIMIT_VIOLATION = 6
    CAPABILITY_VIOLATION = 7
    NO_BACKUP = 8
    NOT_SUPPORTED = 9
    """A command or a compensation term this controller cannot carry out (e.g. a compliance without a force
    reading)."""
    NO_COMMAND = 0xFFFF


class ModbusExceptionCode(IntEnum):
    """Modbus exception codes the controller answers with."""

    ILLEGAL_FUNCTION = 0x01
    ILLEGAL_DATA_ADDRESS = 0x02
    ILLEGAL_DATA_VALUE = 0x03
    SERVER_DEVICE_FAILURE = 0x04
    SERVER_DEVICE_BUSY = 0x06
    GATEWAY_TARGET_FAILED = 0x0B


def words_from_floats(values: Sequence[float]) -> list[int]:
    """float32 values -> registers in ABCD order (values are rounded to float32)."""
    raw = struct.pack(f">{len(values)}f", *values)
    return list(struct.unpack(f">{len(values) * 2}H", raw))


def floats_from_words(words: Sequence[int]) -> list[float]:
    """Registers in ABCD order -> float32 values; ValueError for an odd count or a word outside 0..65535."""
    if len(words) % 2:
        raise ValueError(f"float32 values need an even number of registers, got {len(words)}")
    for i, w in enumerate(words):
        if not isinstance(w, int) or not 0 <= w <= 0xFFFF:
            raise ValueError(f"register {i} holds {w!r}, not a 16-bit word")
    raw = struct.pack(f">{len(words)}H", *words)
    return list(struct.unpack(f">{len(words) // 2}f", raw))


def words_to_bytes(words: Sequence[int]) -> bytes:
    """Registers -> bytes, each register high byte first (the CRC-32 input)."""
    return struct.pack(f">{len(words)}H", *words)


def crc32_of_words(words: Sequence[int]) -> int:
    """CRC-32 of a register block as defined for STAGED_CRC32 / LIVE_CRC32."""
    return crc32_ieee(words_to_bytes(words))


def split_u32(value: int) -> list[int]:
    """uint32 -> [high word, low word]."""
    return [(value >> 16) & 0xFFFF, value & 0xFFFF]


def join_u32(words: Sequence[int]) -> int:
    """[high word, low word] -> uint32."""
    return (words[0] << 16) | words[1]


def parameter_limit_violations(values: Sequence[float]) -> list[str]:
    """Human-readable reasons a 42-value set breaks the sanity bounds (empty list: fine)."""
    problems = []
    for i, (name, v) in enumerate(zip(PARAMETER_NAMES, values, strict=True)):
        if not math.isfinite(v):
            problems.append(f"{name} is not finite ({v})")
        elif i < L0_INDEX and abs(v) > A_B_LIMIT_MM:
            problems.append(f"{name} = {v} mm is beyond +-{A_B_LIMIT_MM} mm")
        elif i >= L0_INDEX and not L0_MIN_MM <= v <= L0_MAX_MM:
            problems.append(f"{name} = {v} mm is outside [{L0_MIN_MM}, {L0_MAX_MM}] mm")
    return problems
