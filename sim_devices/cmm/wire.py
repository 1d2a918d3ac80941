"""The simulated CMM's reader of command lines, written from I++ DME 1.4.3's syntax (6.1.1, 6.1.4.2, 6.2.1, 6.2.2).

``read_command(raw)`` turns one received line into a ``Command`` (tag, method, arguments) or raises ``LineError``
with the error the server answers. It shares only the declarative tables of ``hilcal.protocols.ippdme`` with the
driver. Error numbers for what the specification leaves open follow NIST's reference parser: a bad number or string
0509, a misplaced space or a malformed argument list 0502, a name that is no method of the specification or text
after the closing parenthesis 0507.
"""

from __future__ import annotations

import re
from dataclasses import dataclass

from hilcal.protocols.ippdme import (
    EVENT_METHODS,
    MAX_LINE_CHARS,
    MAX_NUMBER_DIGITS,
    PRINTABLE_MAX,
    PRINTABLE_MIN,
    Code,
    Method,
)

_TAG = re.compile(r"(?!00000)[0-9]{5}")
_ETAG = re.compile(r"E(?!0000)[0-9]{4}")
_BASIC_NAME = re.compile(r"[A-Za-z][A-Za-z0-9]*")
_ETAG_ARGUMENT = re.compile(r"E[0-9]{4}(?![A-Za-z0-9.(])")
_NUMBER_BODY = re.compile(r"[+-]?([0-9]*)(\.?)([0-9]*)")
_EXPONENT = re.compile(r"[Ee][+-]?([0-9]*)")
_SPACES = re.compile(r" +")
_METHODS = frozenset(m.value for m in Method)
_PRINTABLE = bytes(range(PRINTABLE_MIN, PRINTABLE_MAX + 1))


@dataclass(frozen=True)
class Number:
    value: float


@dataclass(frozen=True)
class String:
    value: str


@dataclass(frozen=True)
class Word:
    """A BasicName argument (an enumeration value such as ``MachineCsy``)."""

    value: str


@dataclass(frozen=True)
class EventTag:
    value: str


@dataclass(frozen=True)
class Property:
    """``Name(number, ...)``: a dotted name and its numbers (6.1.4.2 Property)."""

    name: str
    numbers: tuple[float, ...] = ()


Argument = Number | String | Word | EventTag | Property


@dataclass(frozen=True)
class Command:
    tag: str
    method: str
    args: tuple[Argument, ...]

    @property
    def is_event(self) -> bool:
        return self.tag.startswith("E")


class LineError(Exception):
    """A line the server refuses; ``tag`` is None when the tag cannot be read (answered with E0000, 6.2.1)."""

    def __init__(self, code: Code, tag: str | None, method: str = "", detail: str = "") -> None:
        super().__init__(f"{int(code):04d} {detail}")
        self.code = code
        self.tag = tag
        self.method = method
        self.detail = detail


def read_tag(text: str) -> str | None:
    """The tag of a line if it is a valid CommandTag or EventTag (6.2.1), else None."""
    head = text[:5]
    return head if _TAG.fullmatch(head) or _ETAG.fullmatch(head) else None


def read_command(raw: bytes) -> Command:
    """Parse one received line (its LF removed, its CR kept) into a Command; LineError otherwise."""
    text = raw.decode("latin-1")
    tag = read_tag(text)
    if tag is None:
        raise LineError(Code.ILLEGAL_TAG, None, detail=f"tag {text[:5]!r}")
    if not raw.endswith(b"\r"):
        raise LineError(Code.ILLEGAL_CHARACTER, tag, detail="line not ended by CR LF")
    body = raw[:-1]
    if body.translate(None, _PRINTABLE):
        raise LineError(Code.ILLEGAL_CHARACTER, tag, detail="character outside 32..126")
    if len(body) > MAX_LINE_CHARS:
        raise LineError(Code.PROTOCOL_ERROR, tag, detail=f"line longer than {MAX_LINE_CHARS} characters")
    text = body.decode("ascii")
    if text[5:6] != " ":
        raise LineError(Code.NO_SPACE_AT_POS_6, tag)
    return _Reader(text, tag).command()


class _Reader:
    """Recursive descent over ``Method :== BasicName SLeftParenS MethodArgList SRightParen`` from column 7."""

    def __init__(self, text: str, tag: str) -> None:
        self.text = text
        self.tag = tag
        self.pos = 6
        self.method = ""

    def fail(self, code: Code, detail: str) -> LineError:
        return LineError(code, self.tag, self.method, f"{detail} at column {self.pos + 1}")

    def peek(self) -> str:
        return self.text[self.pos : self.pos + 1]

    def spaces(self) -> None:
        while self.peek() == " ":
            self.pos += 1

    def command(self) -> Command:
        _check_spaces(self.text, self.tag)
        m = _BASIC_NAME.match(self.text, self.pos)
        if m is None:
            raise self.fail(Code.ILLEGAL_COMMAND, "no method name")
        if m.group() not in _METHODS:
            raise LineError(Code.ILLEGAL_COMMAND, self.tag, "", f"{m.group()[:40]} is no method of I++ DME 1.4.3")
        self.method = m.group()
        self.pos = m.end()
        self.spaces()
        if self.peek() != "(":
            raise self.fail(Code.INCORRECT_ARGUMENTS, "expected '('")
        self.pos += 1
        self.spaces()
        args: list[Argument] = []
        if self.peek() != ")":
            while True:
                args.append(self.argument())
                self.spaces()
                if self.peek() == ",":
                    self.pos += 1
                    self.spaces()
                    continue
                if self.peek() != ")":
                    raise self.fail(Code.INCORRECT_ARGUMENTS, "expected ',' or ')'")
                break
        self.pos += 1
        if self.pos != len(self.text):
            raise self.fail(Code.ILLEGAL_COMMAND, "text after the method's ')'")
        if (self.method in EVENT_METHODS) != self.tag.startswith("E"):
            raise LineError(Code.ILLEGAL_TAG, None, self.method,
                            f"{self.tag}: only the event methods take an event tag (6.2.1)")
        return Command(self.tag, self.method, tuple(args))

    def argument(self) -> Argument:
        c = self.peek()
        if c == '"':
            end = self.text.find('"', self.pos + 1)
            if end < 0 or end == self.pos + 1:
                raise self.fail(Code.BAD_ARGUMENT, "a string needs one character or more and its closing quote")
            value = self.text[self.pos + 1 : end]
            self.pos = end + 1
            return String(value)
        if c and (c in "+-." or c.isdigit()):
            return Number(self.number())
        tag = _ETAG_ARGUMENT.match(self.text, self.pos)
        if tag is not None:
            self.pos = tag.end()
            return EventTag(tag.group())
        name = self.name()
        if name is None:
            raise self.fail(Code.INCORRECT_ARGUMENTS, "expected an argument")
        self.spaces()
        if self.peek() != "(":
            if "." in name:
                raise self.fail(Code.INCORRECT_ARGUMENTS, f"{name} needs its parentheses")
            return Word(name)
        self.pos += 1
        self.spaces()
        numbers: list[float] = []
        if self.peek() != ")":
            while True:
                c = self.peek()
                if not (c and (c in "+-." or c.isdigit())):
                    raise self.fail(Code.INCORRECT_ARGUMENTS, f"{name}: expected a number")
                numbers.append(self.number())
                self.spaces()
                if self.peek() == ",":
                    self.pos += 1
                    self.spaces()
                    continue
                if self.peek() != ")":
                    raise self.fail(Code.INCORRECT_ARGUMENTS, f"{name}: expected ',' or ')'")
                break
        self.pos += 1
        return Property(name, tuple(numbers))

    def name(self) -> str | None:
        """``Name :== BasicName {"." BasicName}``."""
        parts: list[str] = []
        while True:
            m = _BASIC_NAME.match(self.text, self.pos)
            if m is None:
                if parts:
                    raise self.fail(Code.INCORRECT_ARGUMENTS, "a name may not end with '.'")
                return None
            parts.append(m.group())
            self.pos = m.end()
            if self.peek() != ".":
                return ".".join(parts)
            self.pos += 1

    def number(self) -> float:
        """``Number`` of 6.1.4.2: a sign, digits with one optional point, an exponent of 1..3 digits; at most 16
        digits before the exponent (as NIST's parsers count, and its part programs use: 16 digits and an exponent)."""
        m = _NUMBER_BODY.match(self.text, self.pos)
        assert m is not None
        if "." in self.text[m.end() : m.end() + 1]:
            raise self.fail(Code.BAD_ARGUMENT, "a number with two decimal points")
        digits = len(m.group(1)) + len(m.group(3))
        if digits == 0:
            raise self.fail(Code.BAD_ARGUMENT, "a number without digits")
        end = m.end()
        exponent = _EXPONENT.match(self.text, end)
        if exponent is not None:
            if not 1 <= len(exponent.group(1)) <= 3:
                raise self.fail(Code.BAD_ARGUMENT, "an exponent needs one to three digits")
            end = exponent.end()
        if digits > MAX_NUMBER_DIGITS:
            raise self.fail(Code.BAD_ARGUMENT, f"a number of more than {MAX_NUMBER_DIGITS} digits")
        value = float(self.text[self.pos : end])
        self.pos = end
        return value


def _check_spaces(text: str, tag: str) -> None:
    """6.1.4.2: optional spaces only before or after a comma or a left parenthesis, before a right one, or inside a
    string; the method starts at column 7. Each run of spaces outside a String is checked where it stands: its first
    space may follow "(" or ",", a second one follows a space."""
    for run in _SPACES.finditer(text, 6):
        if text.count('"', 6, run.start()) % 2 or text[run.end():run.end() + 1] in ("(", ")", ","):
            continue
        i = run.start() if run.start() == 6 or text[run.start() - 1] not in ("(", ",") else run.start() + 1
        if i < run.end():
            raise LineError(Code.INCORRECT_ARGUMENTS, tag, "", f"space not allowed at column {i + 1} (6.1.4.2)")
