"""Server-side parser of the CMM command lines (I++-DME-like ``TAG Name(arg, ...)``), written apart from the driver.

It shares only the declarative protocol tables of ``hilcal.protocols.cmm`` with the driver.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass

from hilcal.protocols.cmm import (
    ENCODING,
    MAX_LINE_BYTES,
    NAME_PATTERN,
    NUMBER_PATTERN,
    PRINTABLE_MAX,
    PRINTABLE_MIN,
    SERVER_TAG,
    STRING_PATTERN,
    ErrorCode,
)


@dataclass(frozen=True)
class Call:
    """``Name(arg, ...)``; args are numbers, strings or calls."""

    name: str
    args: tuple[float | str | Call, ...] = ()


@dataclass(frozen=True)
class ParsedCommand:
    tag: str
    call: Call


class CommandRejected(Exception):
    """A command line the server answers with an error (before any acknowledgement)."""

    def __init__(self, tag: str, code: ErrorCode, detail: str = "", method: str = "") -> None:
        super().__init__(f"{tag}: {code.name} {detail}")
        self.tag = tag
        self.code = code
        self.detail = detail
        self.method = method


_NAME = re.compile(NAME_PATTERN)
_NUMBER = re.compile(NUMBER_PATTERN)
_STRING = re.compile(STRING_PATTERN)
_SPACES = re.compile(" *")
_MAX_DEPTH = 6
_PRINTABLE = bytes(range(PRINTABLE_MIN, PRINTABLE_MAX + 1))


class _Scanner:
    """Recursive-descent reader of ``Name(arg, ...)`` over one command body."""

    def __init__(self, text: str, tag: str) -> None:
        self.text = text
        self.pos = 0
        self.tag = tag

    def fail(self, what: str) -> CommandRejected:
        return CommandRejected(self.tag, ErrorCode.PROTOCOL_ERROR, f"{what} at column {self.pos + 7}")

    def skip_spaces(self) -> None:
        self.pos = _SPACES.match(self.text, self.pos).end()

    def peek(self) -> str:
        return self.text[self.pos] if self.pos < len(self.text) else ""

    def call(self, depth: int) -> Call:
        if depth > _MAX_DEPTH:
            raise self.fail("nesting too deep")
        m = _NAME.match(self.text, self.pos)
        if m is None:
            raise self.fail("expected a name")
        self.pos = m.end()
        if self.peek() != "(":
            raise self.fail("expected '('")
        self.pos += 1
        args: list[float | str | Call] = []
        self.skip_spaces()
        if self.peek() != ")":
            while True:
                self.skip_spaces()
                args.append(self.argument(depth))
                self.skip_spaces()
                if self.peek() == ",":
                    self.pos += 1
                    continue
                break
        if self.peek() != ")":
            raise self.fail("expected ')' or ','")
        self.pos += 1
        return Call(m.group(), tuple(args))

    def argument(self, depth: int) -> float | str | Call:
        for pattern in (_NUMBER, _STRING):
            m = pattern.match(self.text, self.pos)
            if m is not None:
                self.pos = m.end()
                if pattern is _STRING:
                    return m.group()[1:-1]
                value = float(m.group())
                if not math.isfinite(value):
                    raise CommandRejected(self.tag, ErrorCode.ARGUMENT_OUT_OF_RANGE, "number too large")
                return value
        return self.call(depth + 1)


def parse_command_line(raw: bytes) -> ParsedCommand:
    """Parse one command line (terminator removed); raises CommandRejected, nothing else."""
    if len(raw) > MAX_LINE_BYTES:
        raise CommandRejected(SERVER_TAG, ErrorCode.PROTOCOL_ERROR, "line too long")
    head = raw[:5]
    if len(head) < 5 or not head.isdigit() or head == SERVER_TAG.encode():
        raise CommandRejected(SERVER_TAG, ErrorCode.ILLEGAL_TAG)
    tag = head.decode(ENCODING)
    if raw[5:6] != b" ":
        raise CommandRejected(tag, ErrorCode.NO_SPACE_AT_POS_6)
    if raw.translate(None, _PRINTABLE):  # anything left is not printable
        raise CommandRejected(tag, ErrorCode.ILLEGAL_CHARACTER)
    scanner = _Scanner(raw[6:].decode(ENCODING), tag)
    call = scanner.call(0)
    scanner.skip_spaces()
    if scanner.pos != len(scanner.text):
        raise scanner.fail("unexpected text after the command")
    return ParsedCommand(tag, call)


def axes_by_name(call: Call, allowed: tuple[str, ...], required: tuple[str, ...]) -> dict[str, tuple[float, ...]]:
    """``X(x), Y(y), IJK(i, j, k)`` style arguments by name; each argument a call of numbers, names unique."""
    out: dict[str, tuple[float, ...]] = {}
    for arg in call.args:
        if not isinstance(arg, Call) or arg.name not in allowed or arg.name in out:
            raise ValueError(f"unexpected argument {arg!r}")
        if not arg.args or not all(isinstance(a, float) for a in arg.args):
            raise ValueError(f"{arg.name} needs numbers")
        out[arg.name] = tuple(float(a) for a in arg.args)  # type: ignore[arg-type]
    missing = [name for name in required if name not in out]
    if missing:
        raise ValueError(f"missing {', '.join(missing)}")
    for name, values in out.items():
        if len(values) != (3 if name == "IJK" else 1):
            raise ValueError(f"{name} has {len(values)} values")
    return out
