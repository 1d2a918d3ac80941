"""CANopen's codes in words: SDO abort codes, emergency error codes and the error register's bits (CiA 301), and
the drive profile's emergency codes (CiA 402), so that a refused write or a fault names its meaning, not a number.

Sources: CiA 301 v4.2.0 §7.2.4.3.17 (protocol SDO abort transfer, table 22 "SDO abort codes"), §7.2.7.3.1
(emergency object, table 21 "Emergency error codes"), §7.5.2.2 (object 1001h error register); CiA 402-2 (IEC
61800-7-201) annex "error codes" for the drive-specific 7xxx/8xxx codes.
"""

from __future__ import annotations

from collections.abc import Mapping

SDO_ABORTS: Mapping[int, str] = {
    0x05030000: "toggle bit not alternated",
    0x05040000: "SDO protocol timed out",
    0x05040001: "client/server command specifier not valid or unknown",
    0x05040002: "invalid block size (block mode only)",
    0x05040003: "invalid sequence number (block mode only)",
    0x05040004: "CRC error (block mode only)",
    0x05040005: "out of memory",
    0x06010000: "unsupported access to an object",
    0x06010001: "attempt to read a write-only object",
    0x06010002: "attempt to write a read-only object",
    0x06020000: "object does not exist in the object dictionary",
    0x06040041: "object cannot be mapped to the PDO",
    0x06040042: "the number and length of the objects to be mapped would exceed the PDO length",
    0x06040043: "general parameter incompatibility reason",
    0x06040047: "general internal incompatibility in the device",
    0x06060000: "access failed due to a hardware error",
    0x06070010: "data type does not match, length of service parameter does not match",
    0x06070012: "data type does not match, length of service parameter too high",
    0x06070013: "data type does not match, length of service parameter too low",
    0x06090011: "sub-index does not exist",
    0x06090030: "invalid value for parameter (download only)",
    0x06090031: "value of parameter written too high (download only)",
    0x06090032: "value of parameter written too low (download only)",
    0x06090036: "maximum value is less than minimum value",
    0x060A0023: "resource not available: SDO connection",
    0x08000000: "general error",
    0x08000020: "data cannot be transferred or stored to the application",
    0x08000021: "data cannot be transferred or stored to the application because of local control",
    0x08000022: "data cannot be transferred or stored to the application because of the present device state",
    0x08000023: "object dictionary dynamic generation fails or no object dictionary is present",
    0x08000024: "no data available",
}
"""CiA 301 v4.2.0 §7.2.4.3.17, table 22."""

EMCY_CODES: Mapping[int, str] = {
    0x0000: "error reset or no error",
    0x1000: "generic error",
    0x2000: "current",
    0x2100: "current, device input side",
    0x2200: "current inside the device",
    0x2300: "current, device output side",
    0x3000: "voltage",
    0x3100: "mains voltage",
    0x3200: "voltage inside the device",
    0x3300: "output voltage",
    0x4000: "temperature",
    0x4100: "ambient temperature",
    0x4200: "device temperature",
    0x5000: "device hardware",
    0x6000: "device software",
    0x6100: "internal software",
    0x6200: "user software",
    0x6300: "data set",
    0x7000: "additional modules",
    0x8000: "monitoring",
    0x8100: "communication",
    0x8110: "CAN overrun (objects lost)",
    0x8120: "CAN in error passive mode",
    0x8130: "life guard error or heartbeat error",
    0x8140: "recovered from bus off",
    0x8150: "CAN-ID collision",
    0x8200: "protocol error",
    0x8210: "PDO not processed due to length error",
    0x8220: "PDO length exceeded",
    0x8230: "DAM MPDO not processed, destination object not available",
    0x8240: "unexpected SYNC data length",
    0x8250: "RPDO timeout",
    0x9000: "external error",
    0xF000: "additional functions",
    0xFF00: "device specific",
}
"""CiA 301 v4.2.0 §7.2.7.3.1, table 21 (the classes xx00 and the communication codes)."""

DRIVE_EMCY_CODES: Mapping[int, str] = {
    0x7300: "sensor",
    0x7310: "speed sensor",
    0x7320: "position sensor",
    0x8400: "velocity speed controller",
    0x8500: "position controller",
    0x8600: "positioning controller",
    0x8611: "following error",
    0x8612: "reference limit",
}
"""CiA 402-2 (IEC 61800-7-201), the drive-specific emergency codes the driver names."""

ERROR_REGISTER_BITS: tuple[str, ...] = (
    "generic error", "current", "voltage", "temperature", "communication error (overrun, error state)",
    "device profile specific", "reserved", "manufacturer-specific",
)
"""Object 1001h, bits 0..7 (CiA 301 v4.2.0 §7.5.2.2)."""


def sdo_abort_text(code: int) -> str:
    """``0x06010002 (attempt to write a read-only object)``; an unlisted code says so."""
    meaning = SDO_ABORTS.get(code)
    if meaning is None:
        meaning = "manufacturer-specific or unknown abort code" if code >> 24 not in (5, 6, 8) else "not in CiA 301"
    return f"0x{code:08X} ({meaning})"


def emcy_text(code: int, vendor: Mapping[int, str] | None = None) -> str:
    """An emergency error code in words: the vendor's name for it (the station's mapping), else CiA 402's or CiA
    301's exact code, else its class (the code with the low byte, then the low 12 bits cleared)."""
    for table in (vendor or {}, DRIVE_EMCY_CODES, EMCY_CODES):
        if code in table:
            return f"0x{code:04X} ({table[code]})"
    for base in (code & 0xFFF0, code & 0xFF00, code & 0xF000):
        for table in (DRIVE_EMCY_CODES, EMCY_CODES):
            if base in table:
                return f"0x{code:04X} ({table[base]})"
    return f"0x{code:04X} (unknown)"


def error_register_text(value: int) -> str:
    """Object 1001h's set bits in words: ``0x09 (generic error, temperature)``; 0 is ``0x00 (no error)``."""
    names = [name for bit, name in enumerate(ERROR_REGISTER_BITS) if value >> bit & 1]
    return f"0x{value:02X} ({', '.join(names) if names else 'no error'})"
