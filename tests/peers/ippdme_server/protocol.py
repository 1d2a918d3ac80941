"""I++ DME 1.4.3 protocol layer: error table, line parser and response formatting.

Everything here is pure (no sockets, no machine state):

* ``ERRORS`` - the predefined error list of spec section 8.2 (default severity, text).
* ``IppError`` - an error to be reported as ``tag ! Error(F1, F2, F3, Text)`` (section 8.1).
* ``parse_tag`` / ``parse_method`` - the CommandLine syntax of sections 6.1.1, 6.1.4.2, 6.2.1
  and 6.2.2.1.
* ``validate_response`` - a checker for ResponseLines (section 6.1.4.2 / 6.2.2.2), used by the
  self check and usable by tests.
* ``fmt_number`` - number formatting that always satisfies the ``Number`` production.
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field

#: Section 8.2: error number -> (default severity class, text).
ERRORS: dict[int, tuple[int, str]] = {
    0: (0, "Buffer full"),
    1: (2, "Illegal tag"),
    2: (2, "No space at pos. 6"),
    3: (2, "Reserved"),
    4: (2, "Reserved"),
    5: (2, "Reserved"),
    6: (2, "Transaction aborted (Use ClearAllErrors To Continue)"),
    7: (3, "Illegal character"),
    8: (3, "Protocol error"),
    500: (3, "Emergency stop"),
    501: (3, "Unsupported command"),
    502: (3, "Incorrect arguments"),
    503: (9, "Controller communications failure"),
    504: (1, "Argument out of range"),
    505: (3, "Argument not recognized"),
    506: (3, "Argument not supported"),
    507: (3, "Illegal command"),
    508: (3, "Bad context"),
    509: (3, "Bad argument"),
    510: (3, "Bad property"),
    511: (3, "Error processing method"),
    512: (1, "No daemons are active"),
    513: (2, "Daemon does not exist"),
    514: (2, "Use ClearAllErrors to continue"),
    515: (2, "Daemon already exists"),
    1000: (3, "Machine in error state"),
    1001: (2, "Illegal touch"),
    1002: (9, "Axis does not exist"),
    1003: (2, "No touch"),
    1004: (9, "Number of angles not supported on current device"),
    1005: (3, "Error during home"),
    1006: (2, "Surface not found"),
    1007: (3, "Theta out of range"),
    1008: (3, "Target position out of machine volume"),
    1009: (3, "Air pressure out of range"),
    1010: (2, "Vector has no norm"),
    1011: (2, "Unable to move"),
    1012: (2, "Bad lock combinations"),
    1500: (3, "Failed to re-seat head"),
    1501: (3, "Probe not armed"),
    1502: (3, "Tool not found"),
    1503: (3, "Tool not defined"),
    2000: (3, "Tool not calibrated"),
    2001: (2, "Head error excessive force"),
    2002: (3, "Type of probe does not allow this operation"),
    2500: (3, "Machine limit encountered [Move Out Of Limits]"),
    2501: (3, "Axis not active"),
    2502: (3, "Axis position error"),
    2503: (9, "Scale read head failure"),
    2504: (3, "Collision"),
    2505: (2, "Specified angle out of range"),
    2506: (2, "Part not aligned"),
}

#: Maximum CommandLine length (section 6.2, "should not exceed 65536").
MAX_LINE = 65536


class IppError(Exception):
    """An I++ error (section 8.1).

    ``method`` becomes field F3 (the spec recommends the name of the error causing method);
    ``detail`` is a free text kept for the server's own transcript only.  ``record`` is False
    for follow-up errors (0511/0514) that must not change the stored error state.
    """

    def __init__(self, code: int, method: str = "", detail: str = "", *,
                 severity: int | None = None, record: bool = True,
                 preceding: tuple[IppError, ...] = ()) -> None:
        default_severity, text = ERRORS[code]
        self.code = code
        self.severity = default_severity if severity is None else severity
        self.text = text
        self.method = method or "Server"
        self.detail = detail
        self.record = record
        self.preceding = preceding
        super().__init__(f"{code:04d} {text}: {detail}" if detail else f"{code:04d} {text}")

    def payload(self) -> str:
        """The part of the ResponseLine after ``"tag ! "`` (ErrorResponse, 6.1.4.2)."""
        return f'Error({self.severity}, {self.code:04d}, "{self.method}", "{self.text}")'


class LineError(Exception):
    """A CommandLine so malformed that no valid tag can be associated with it.

    Reported with the reserved tag E0000 (section 6.2.1: "The Illegal tag error message should
    be reported by the E0000 tag").
    """

    def __init__(self, error: IppError) -> None:
        super().__init__(str(error))
        self.error = error


# --------------------------------------------------------------------------- arguments

@dataclass(frozen=True)
class StrArg:
    """``String`` argument (quotes removed)."""

    value: str


@dataclass(frozen=True)
class NumArg:
    """``Number`` argument; ``text`` keeps the original spelling."""

    value: float
    text: str


@dataclass(frozen=True)
class PropArg:
    """``Property`` argument: dotted ``Name`` with a (possibly empty) list of numbers."""

    name: str
    values: tuple[float, ...] = ()


@dataclass(frozen=True)
class TagArg:
    """``ETag`` argument, e.g. the daemon tag of ``StopDaemon(E0005)``."""

    tag: str


@dataclass(frozen=True)
class WordArg:
    """``BasicName`` argument, e.g. ``MachineCsy`` (enumerations are unquoted, 6.3.3.1)."""

    word: str


Argument = StrArg | NumArg | PropArg | TagArg | WordArg


@dataclass(frozen=True)
class Command:
    """A parsed CommandLine (section 6.2.2.1)."""

    tag: str
    name: str
    args: tuple[Argument, ...] = field(default_factory=tuple)

    @property
    def is_event(self) -> bool:
        """True for an EventTag (``E0001`` .. ``E9999``)."""
        return self.tag.startswith("E")


# --------------------------------------------------------------------------- scanner

_NUMBER_RE = re.compile(r"[+-]?(?:[0-9]+\.?[0-9]*|\.[0-9]+)(?:[eE][+-]?[0-9]+)?")
_NAME_RE = re.compile(r"[A-Za-z][A-Za-z0-9]*(?:\.[A-Za-z][A-Za-z0-9]*)*")
_ETAG_RE = re.compile(r"E[0-9]{4}")
_TAG_RE = re.compile(r"E[0-9]{4}|[0-9]{5}")


class _SyntaxProblem(Exception):
    """Internal: the text does not match the production being parsed."""


class _Scanner:
    """Character scanner for the productions of section 6.1.4.2."""

    def __init__(self, text: str, pos: int = 0) -> None:
        self.text = text
        self.pos = pos

    def at_end(self) -> bool:
        return self.pos >= len(self.text)

    def peek(self) -> str:
        return self.text[self.pos] if self.pos < len(self.text) else ""

    def skip_spaces(self) -> None:
        while self.peek() == " ":
            self.pos += 1

    def expect(self, char: str) -> None:
        if self.peek() != char:
            raise _SyntaxProblem(f"expected {char!r} at column {self.pos + 1}")
        self.pos += 1

    def name(self) -> str:
        match = _NAME_RE.match(self.text, self.pos)
        if not match:
            raise _SyntaxProblem(f"expected a name at column {self.pos + 1}")
        self.pos = match.end()
        return match.group()

    def number(self) -> NumArg:
        match = _NUMBER_RE.match(self.text, self.pos)
        if not match:
            raise _SyntaxProblem(f"expected a number at column {self.pos + 1}")
        text = match.group()
        mantissa, _, exponent = text.lower().partition("e")
        if exponent and not 1 <= len(exponent.lstrip("+-")) <= 3:
            raise _SyntaxProblem(f"exponent of {text!r} must have one to three digits")
        if sum(ch.isdigit() for ch in mantissa) > 16:
            raise _SyntaxProblem(f"{text!r} has more than 16 digits")
        self.pos = match.end()
        return NumArg(float(text), text)

    def string(self) -> StrArg:
        self.expect('"')
        end = self.text.find('"', self.pos)
        if end < 0:
            raise _SyntaxProblem("unterminated string")
        if end == self.pos:
            raise _SyntaxProblem("empty string")
        value = self.text[self.pos:end]
        self.pos = end + 1
        return StrArg(value)

    def list_of(self, parse_item) -> list:
        """``SLeftParenS [item {SCommaS item}] SRightParen`` (the opening paren is next)."""
        self.skip_spaces()
        self.expect("(")
        self.skip_spaces()
        items: list = []
        if self.peek() == ")":
            self.pos += 1
            return items
        while True:
            items.append(parse_item())
            self.skip_spaces()
            if self.peek() == ",":
                self.pos += 1
                self.skip_spaces()
                continue
            self.expect(")")
            return items

    def paren_follows(self) -> bool:
        """True if optional spaces and then ``(`` follow (without consuming them)."""
        pos = self.pos
        while pos < len(self.text) and self.text[pos] == " ":
            pos += 1
        return pos < len(self.text) and self.text[pos] == "("

    def command_argument(self) -> Argument:
        """``Argument :== String | Number | Property | ETag | BasicName``."""
        char = self.peek()
        if char == '"':
            return self.string()
        if char.isdigit() or char in "+-.":
            return self.number()
        if not char.isalpha():
            raise _SyntaxProblem(f"unexpected {char!r} at column {self.pos + 1}")
        name = self.name()
        if self.paren_follows():
            values = self.list_of(self.number)
            return PropArg(name, tuple(v.value for v in values))
        if "." in name:
            raise _SyntaxProblem(f"property {name!r} needs parentheses")
        if _ETAG_RE.fullmatch(name) and name != "E0000":
            return TagArg(name)
        return WordArg(name)

    def response_item(self) -> None:
        """Lenient DataResponse item: String, Number or Name with optional nested list."""
        char = self.peek()
        if char == '"':
            self.string()
        elif char.isdigit() or char in "+-.":
            self.number()
        elif char.isalpha():
            self.name()
            if self.paren_follows():
                self.list_of(self.response_item)
        else:
            raise _SyntaxProblem(f"unexpected {char!r} at column {self.pos + 1}")


# --------------------------------------------------------------------------- commands

def check_characters(line: str) -> bool:
    """Section 6.1.1: only ASCII 32..126 may appear inside a line."""
    return all(32 <= ord(ch) <= 126 for ch in line)


def parse_tag(line: str) -> str:
    """Return the CommandTag/EventTag of ``line`` (sections 6.2.1, 6.2.2.1).

    Raises ``LineError`` (error 0001 or 0002) when no legal tag followed by a space exists.
    """
    tag = line[:5]
    if not _TAG_RE.fullmatch(tag) or tag in ("00000", "E0000"):
        raise LineError(IppError(1, "Parser", f"illegal tag in {line[:16]!r}"))
    if len(line) < 6 or line[5] != " ":
        raise LineError(IppError(2, "Parser", f"no space after tag {tag}"))
    return tag


def parse_method(tag: str, line: str) -> Command:
    """Parse ``Method`` starting at column 7 (``Command :== (Tag | ETag) s Method``).

    Raises ``IppError`` 0507 when no method name can be read and 0502 when the argument
    list violates the grammar of section 6.1.4.2 (spaces, numbers, strings, parentheses).
    """
    scanner = _Scanner(line, 6)
    try:
        name = scanner.name()
    except _SyntaxProblem as problem:
        raise IppError(507, "Parser", str(problem)) from None
    if "." in name or not scanner.paren_follows():
        raise IppError(507, "Parser", f"{name!r} is not a method call")
    try:
        args = scanner.list_of(scanner.command_argument)
        if not scanner.at_end():
            raise _SyntaxProblem(f"unexpected text after ')' at column {scanner.pos + 1}")
    except _SyntaxProblem as problem:
        raise IppError(502, name, str(problem)) from None
    return Command(tag, name, tuple(args))


# --------------------------------------------------------------------------- responses

_ERROR_RE = re.compile(
    r'Error {0,}\( {0,}([0-9]) {0,}, {0,}([0-9]{4}) {0,}, {0,}"([^"]+)" {0,}, {0,}"([^"]+)" {0,}\)')


def validate_response(line: str) -> str:
    """Check a ResponseLine against sections 6.1.4.2 / 6.2.2.2; return its kind character.

    Data lines are checked leniently: a comma separated list of strings, numbers and names with
    optional (nested) argument lists, which covers every data format of the spec (e.g.
    ``Tool.Name("Probe1")`` and bare strings as in the EnumTools example of 6.3.2.23).
    Raises ``ValueError`` with a reason if the line is malformed.
    """
    if not check_characters(line):
        raise ValueError("illegal character")
    tag = line[:5]
    if not _TAG_RE.fullmatch(tag) or tag == "00000":
        raise ValueError(f"bad tag {tag!r}")
    if len(line) < 7 or line[5] != " " or line[6] not in "&%#!":
        raise ValueError("column 6 must be a space and column 7 one of & % # !")
    kind = line[6]
    if kind in "&%":
        if len(line) != 7:
            raise ValueError("ack/complete lines must end at column 7")
        return kind
    if len(line) < 9 or line[7] != " ":
        raise ValueError("column 8 must be a space")
    body = line[8:]
    if kind == "!":
        match = _ERROR_RE.fullmatch(body)
        if not match:
            raise ValueError("malformed ErrorResponse")
        code = int(match.group(2))
        if code in ERRORS and match.group(4) != ERRORS[code][1]:
            raise ValueError(f"text of error {code:04d} differs from section 8.2")
        return kind
    scanner = _Scanner(body)
    try:
        while True:
            scanner.response_item()
            scanner.skip_spaces()
            if scanner.at_end():
                break
            scanner.expect(",")
            scanner.skip_spaces()
    except _SyntaxProblem as problem:
        raise ValueError(f"malformed data: {problem}") from None
    if body.endswith(" "):
        raise ValueError("trailing space")
    return kind


def fmt_number(value: float, decimals: int = 6) -> str:
    """Format a number per the ``Number`` production (fixed point, at most 16 digits)."""
    text = f"{value:.{decimals}f}"
    while sum(ch.isdigit() for ch in text) > 16 and decimals > 0:
        decimals -= 1
        text = f"{value:.{decimals}f}"
    if float(text) == 0.0:
        text = text.lstrip("-")
    return text
