"""SLCAN (Lawicel ASCII) line protocol, server side: parse one host line, split a byte stream into lines."""

from __future__ import annotations

from dataclasses import dataclass


class SlcanError(ValueError):
    """A line that is not a valid SLCAN command (answered with BEL)."""


@dataclass(frozen=True)
class SlcanCommand:
    """One parsed SLCAN line; frame fields are set for t/T/r/R."""

    code: str
    argument: str = ""
    frame_id: int | None = None
    data: bytes = b""
    extended: bool = False
    remote: bool = False


MAX_LINE_BYTES = 64
_HEX = frozenset("0123456789abcdefABCDEF")
_NO_ARGUMENT = frozenset("OCLVvNF")


def _hex(text: str, what: str) -> int:
    if not text or not set(text) <= _HEX:
        raise SlcanError(f"{what}: {text!r} is not hexadecimal")
    return int(text, 16)


def parse_slcan_line(line: bytes) -> SlcanCommand:
    """Parse one line (without its CR) sent by a host to an SLCAN adapter."""
    try:
        text = line.decode("ascii")
    except UnicodeDecodeError:
        raise SlcanError("non-ASCII bytes") from None
    if not text.isprintable():
        raise SlcanError("control characters in line")
    if not text:
        return SlcanCommand("")
    code, arg = text[0], text[1:]
    if code in "tTrR":
        id_digits = 8 if code in "TR" else 3
        if len(arg) < id_digits + 1:
            raise SlcanError(f"frame line too short: {text!r}")
        frame_id = _hex(arg[:id_digits], "identifier")
        if frame_id > (0x1FFFFFFF if id_digits == 8 else 0x7FF):
            raise SlcanError(f"identifier 0x{frame_id:X} out of range")
        dlc_char = arg[id_digits]
        if dlc_char not in "012345678":
            raise SlcanError(f"DLC {dlc_char!r} is not 0..8")
        dlc = int(dlc_char)
        payload = arg[id_digits + 1:]
        remote = code in "rR"
        if remote:
            if payload:
                raise SlcanError("remote frame with data")
            data = b""
        else:
            if len(payload) != 2 * dlc:
                raise SlcanError(f"{len(payload)} data digits for DLC {dlc}")
            if not set(payload) <= _HEX:
                raise SlcanError("data is not hexadecimal")
            data = bytes.fromhex(payload)
        return SlcanCommand(code, arg, frame_id, data, extended=code in "TR", remote=remote)
    if code in _NO_ARGUMENT:
        if arg:
            raise SlcanError(f"command {code!r} takes no argument")
        return SlcanCommand(code)
    if code == "S":
        if len(arg) != 1 or arg not in "012345678":
            raise SlcanError(f"bitrate code {arg!r} is not 0..8")
        return SlcanCommand(code, arg)
    if code == "s":
        if len(arg) != 4:
            raise SlcanError("BTR needs 4 hex digits")
        _hex(arg, "BTR")
        return SlcanCommand(code, arg)
    if code in "ZX":
        if arg not in ("0", "1"):
            raise SlcanError(f"{code} needs 0 or 1")
        return SlcanCommand(code, arg)
    if code in "Mm":
        if len(arg) != 8:
            raise SlcanError("acceptance code/mask needs 8 hex digits")
        _hex(arg, "acceptance")
        return SlcanCommand(code, arg)
    raise SlcanError(f"unsupported command {code!r}")


class SlcanLineSplitter:
    """Split a byte stream into CR-terminated lines; overlong lines become SlcanError items."""

    def __init__(self, max_line_bytes: int = MAX_LINE_BYTES) -> None:
        self._buffer = bytearray()
        self._max = max_line_bytes
        self._overflow = False

    def feed(self, data: bytes) -> list[bytes | SlcanError]:
        self._buffer.extend(data)
        out: list[bytes | SlcanError] = []
        while True:
            end = self._buffer.find(b"\r")
            if end < 0:
                if len(self._buffer) > self._max:
                    self._buffer.clear()
                    self._overflow = True
                return out
            line = bytes(self._buffer[:end]).strip(b"\n")
            del self._buffer[: end + 1]
            if self._overflow or len(line) > self._max:
                self._overflow = False
                out.append(SlcanError("line too long"))
            else:
                out.append(line)
