"""Checksums used on the controller links: CRC-8/SAE-J1850 (CAN frames), CRC-32 (parameter sets), CRC-16/MODBUS.

Pure functions; every definition is the catalogue one (reveng.sourceforge.io "catalogue of parametrised CRC
algorithms") so third-party tools can verify frames.
"""

from __future__ import annotations

import zlib

CRC8_POLY = 0x1D
CRC8_INIT = 0xFF
CRC8_XOROUT = 0xFF


def _crc8_table() -> tuple[int, ...]:
    table = []
    for byte in range(256):
        crc = byte
        for _ in range(8):
            crc = ((crc << 1) ^ CRC8_POLY) & 0xFF if crc & 0x80 else (crc << 1) & 0xFF
        table.append(crc)
    return tuple(table)


_CRC8_TABLE = _crc8_table()


def crc8_sae_j1850(data: bytes) -> int:
    """CRC-8/SAE-J1850: poly 0x1D, init 0xFF, no reflection, xorout 0xFF (check "123456789" = 0x4B)."""
    crc = CRC8_INIT
    for byte in data:
        crc = _CRC8_TABLE[crc ^ byte]
    return crc ^ CRC8_XOROUT


def crc32_ieee(data: bytes) -> int:
    """CRC-32/ISO-HDLC (zlib, Ethernet): poly 0x04C11DB7 reflected, init/xorout 0xFFFFFFFF (check 0xCBF43926)."""
    return zlib.crc32(data) & 0xFFFFFFFF


def crc16_modbus(data: bytes) -> int:
    """CRC-16/MODBUS: poly 0x8005 reflected (0xA001), init 0xFFFF, no xorout (check "123456789" = 0x4B37)."""
    crc = 0xFFFF
    for byte in data:
        crc ^= byte
        for _ in range(8):
            crc = (crc >> 1) ^ 0xA001 if crc & 1 else crc >> 1
    return crc


CAN_PAYLOAD_BYTES = 8
CAN_COUNTER_BYTE = 6
CAN_CHECKSUM_BYTE = 7
CAN_COUNTER_MODULO = 16


def can_frame_checksum(frame_id: int, data: bytes) -> int:
    """Checksum byte of a controller CAN frame: CRC-8/SAE-J1850 over the 11-bit ID (2 bytes, big-endian)
    followed by payload bytes 0..6 (the checksum byte 7 itself is excluded).

    Including the ID catches a frame whose identifier was corrupted into another valid identifier.
    """
    return crc8_sae_j1850(bytes(((frame_id >> 8) & 0x07, frame_id & 0xFF)) + bytes(data[:CAN_CHECKSUM_BYTE]))
