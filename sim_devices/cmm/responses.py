"""The simulated CMM's formatter of response lines (6.2.2.2, 6.1.4.2) and of the errors of 8.2.

Numbers are printed with at most 16 digits (6.1.4.2), coordinates to the nanometre; an error line carries the
table's default severity and exact text (8.1: "The text string must be the text string shown in section 8.2"), and
F3 is a String naming the method or server function that reported it (8.1).
"""

from __future__ import annotations

from hilcal.protocols.ippdme import ENCODING, ERRORS, PRINTABLE_MAX, PRINTABLE_MIN, TERMINATOR, Code, Marker

COORDINATE_DECIMALS = 6
SERVER_EVENT_TAG = "E0000"


def number(value: float) -> str:
    """A Number of 6.1.4.2 (at most 16 digits): fixed point to 1 nm for lengths and angles of the machine."""
    text = f"{value:.{COORDINATE_DECIMALS}f}"
    if sum(c.isdigit() for c in text) > 16:
        text = f"{value:.9e}"
    return "0.000000" if text == "-0.000000" else text


def string(value: str) -> str:
    """A String of 6.1.4.2: quoted, printable, no double quote inside, not empty."""
    safe = "".join(c if PRINTABLE_MIN <= ord(c) <= PRINTABLE_MAX and c != '"' else "'" for c in value)
    return f'"{safe or "?"}"'


def line(tag: str, marker: Marker, data: str = "") -> bytes:
    """One response line with its CR LF: ``tag &``, ``tag %``, ``tag # data`` or ``tag ! data``."""
    text = f"{tag} {marker}" + (f" {data}" if data else "")
    return text.encode(ENCODING) + TERMINATOR


def error_data(code: Code | int, where: str) -> str:
    """``Error(F1, F2, F3, Text)`` with the default severity and text of 8.2."""
    spec = ERRORS[int(code)]
    return f"Error({int(spec.severity)}, {int(code):04d}, {string(where)}, {string(spec.text)})"


def error_line(tag: str, code: Code | int, where: str) -> bytes:
    return line(tag, Marker.ERROR, error_data(code, where))


def severity(code: Code | int) -> int:
    return int(ERRORS[int(code)].severity)
