"""I++ DME 1.4.3 lines as the CMM driver reads and writes them: the syntax of 6.1.4.2 (characters 6.1.1, tags 6.2.1,
layout 6.2.2) for the response lines it receives and for the command lines it sends, and the command formatter.

The driver's own parser and formatter: only the tables of ``hilcal.protocols.ippdme`` are shared with the simulated
CMM. A response line parses into its tag, its marker (6.2.2.2) and its data or error; what the data mean (the forms
of section 6.3 and the error table of 8.2) is checked by ``drivers.cmm.forms``.

Where the grammar of 6.1.4.2 is narrower than the data forms the specification itself defines, the wider form is
parsed: a single String (GetErrorInfo 6.3.1.6, EnumTools 6.3.2.23), a property with a String or enumeration argument
(``Tool.Name("x")`` 6.3.10, ``Tool.CollisionVolume(OBB, ...)`` 6.3.11), and NIST's reference server's parenthesised
number list for AlignTool/AlignPart (``(0.6, 0, 0.8)``; the specification gives that data no form); F3 of an error may
be a bare name as in the examples of 6.2.3.1 and 6.3.1.7 and as 8.1 says ("no need for putting into quotes"), although
the grammar says String. ``drivers.cmm.forms`` reports those as what they are.
"""

from __future__ import annotations

import re
from collections.abc import Callable
from dataclasses import dataclass
from enum import StrEnum
from typing import NamedTuple, TypeVar

from hilcal.protocols.ippdme import (
    EVENT_METHODS,
    MAX_LINE_CHARS,
    MAX_NUMBER_DIGITS,
    PRINTABLE_MAX,
    PRINTABLE_MIN,
    SERVER_EVENT_TAG,
    TAG_MAX,
    TAG_MIN,
    Marker,
)

MAX_NESTING = 8
"""Deepest nesting of ``Name(...)`` the parser follows (the specification's forms need 3)."""
_BASIC = re.compile(r"[A-Za-z][A-Za-z0-9]*")
_COMMAND_TAG = re.compile(r"[0-9]{5}")
_EVENT_TAG = re.compile(r"E[0-9]{4}")
_T = TypeVar("_T")


class LineSyntaxError(ValueError):
    """A line that breaks the syntax of 6.1.4.2 / 6.2: the reason and the column (1-based) where it was found."""

    def __init__(self, line: str, reason: str, column: int | None = None) -> None:
        where = "" if column is None else f" at column {column}"
        super().__init__(f"{reason}{where}: {line[:120]!r}")
        self.line = line
        self.reason = reason
        self.column = column


@dataclass(frozen=True)
class Word:
    """A bare name as an argument: an enumeration value (``CartCMM``, ``MachineCsy``, ``Switch``, ``OBB``) or an
    E-tag (``StopDaemon(E0005)``)."""

    name: str

    def __str__(self) -> str:
        return self.name


@dataclass(frozen=True)
class Item:
    """``Name(arg, ...)``: a property, a method, a report item; args are numbers, Strings (``str``), ``Word`` or
    nested items."""

    name: str
    args: tuple[Arg, ...] = ()

    def __str__(self) -> str:
        return f"{self.name}({', '.join(format_arg(a) for a in self.args)})"


Arg = float | str | Word | Item


class Form(StrEnum):
    """What a data response holds (6.1.4.2 DataData, widened as the module docstring says)."""

    NUMBERS = "numbers"
    """NumData: scan data."""
    STRINGS = "strings"
    """One String (GetErrorInfo, EnumTools) or PropData, two (EnumProp)."""
    ITEMS = "items"
    """Method or PropertyList: ``Name(...)``, ..."""
    VECTOR = "vector"
    """``(n, n, n)``: NIST's reference server's AlignTool/AlignPart data."""


@dataclass(frozen=True)
class ErrorReport:
    """``! Error(F1, F2, F3, Text)`` (6.1.4.2, 8.1)."""

    severity: int
    code: int
    method: str
    """F3: where the server says the error arose."""
    text: str
    method_quoted: bool = True
    """False: F3 was sent as a bare name, not the String of 6.1.4.2."""


@dataclass(frozen=True)
class ResponseLine:
    """One response line (6.2.2.2), parsed."""

    raw: str
    tag: str
    marker: Marker
    form: Form | None = None
    values: tuple[Arg, ...] = ()
    error: ErrorReport | None = None

    @property
    def is_server_event(self) -> bool:
        """Sent with E0000: unsolicited (6.2.4, 9.5)."""
        return self.tag == SERVER_EVENT_TAG

    def items(self) -> dict[str, Item]:
        """The data items by name (the last of a name wins; ``drivers.cmm.forms`` flags a name given twice)."""
        return {v.name: v for v in self.values if isinstance(v, Item)}


# ---------------------------------------------------------------------- tokens


class _Tok(NamedTuple):
    kind: str  # "num", "str", "name", "(", ")", ","
    text: str
    column: int
    gap: bool
    """Whitespace stood before it."""
    value: float | str | None = None


_OUTSIDE = re.compile(f"[^{chr(PRINTABLE_MIN)}-{re.escape(chr(PRINTABLE_MAX))}]")
_PLAIN_NUMBER = re.compile(r"[+-]?(?:(\d+)(?:\.(\d*))?|\.(\d+))(?:[Ee][+-]?\d{1,3})?(?![0-9A-Za-z\"_.])")
"""A well-formed Number (6.1.4.2) not run into what follows it; ``_number`` names what is wrong with any other."""


def _check_characters(line: str) -> None:
    """6.1.1: ASCII 32..126 only (the CR LF terminator is removed before parsing); 6.2: the line length."""
    if len(line) > MAX_LINE_CHARS:
        raise LineSyntaxError(line, f"line longer than {MAX_LINE_CHARS} characters")
    bad = _OUTSIDE.search(line)
    if bad is not None:
        raise LineSyntaxError(line, f"character {ord(bad.group())} outside ASCII 32..126 (6.1.1)", bad.start() + 1)


def _number(line: str, k: int) -> tuple[str, int]:
    """The Number starting at k (6.1.4.2) and where it ends; LineSyntaxError for a malformed one. "The total number
    of digits shall not exceed 16" is read as NIST's parsers and ``numbersCmdOK.prg`` read it: the digits before the
    exponent (``+1.234567890123456E003`` is a good number there)."""
    plain = _PLAIN_NUMBER.match(line, k)
    if plain is not None and sum(len(g) for g in plain.groups() if g) <= MAX_NUMBER_DIGITS:
        return plain.group(), plain.end()
    start = k
    if k < len(line) and line[k] in "+-":
        k += 1
    digits = 0
    while k < len(line) and line[k].isdigit():
        k, digits = k + 1, digits + 1
    if k < len(line) and line[k] == ".":
        k += 1
        while k < len(line) and line[k].isdigit():
            k, digits = k + 1, digits + 1
    if digits == 0:
        raise LineSyntaxError(line, "a number without digits", start + 1)
    if k < len(line) and line[k] == ".":
        raise LineSyntaxError(line, "a number with two decimal points", start + 1)
    if digits > MAX_NUMBER_DIGITS:
        raise LineSyntaxError(line, f"a number with more than {MAX_NUMBER_DIGITS} digits", start + 1)
    if k < len(line) and line[k] in "Ee":
        k += 1
        if k < len(line) and line[k] in "+-":
            k += 1
        exp = 0
        while k < len(line) and line[k].isdigit():
            k, exp = k + 1, exp + 1
        if not 1 <= exp <= 3:
            raise LineSyntaxError(line, "an exponent must have one, two or three digits", start + 1)
    if k < len(line) and line[k] == ".":
        raise LineSyntaxError(line, "a number with two decimal points", start + 1)
    if k < len(line) and (line[k].isalnum() or line[k] in "\"_"):
        raise LineSyntaxError(line, f"bad character {line[k]!r} after a number", k + 1)
    return line[start:k], k


def _name(line: str, k: int) -> tuple[str, int]:
    """Name :== BasicName {"." BasicName} starting at k."""
    start = k
    while True:
        m = _BASIC.match(line, k)
        if m is None:
            raise LineSyntaxError(line, "a name part must start with a letter", k + 1)
        k = m.end()
        if k < len(line) and line[k] == ".":
            k += 1
            continue
        return line[start:k], k


def _tokens(line: str, start: int) -> list[_Tok]:
    """The tokens of line[start:], with the optional-space rule of 6.1.4.2 enforced: spaces only before or after a
    comma, before or after "(", and before ")"."""
    toks: list[_Tok] = []
    k, gap = start, False
    while k < len(line):
        ch = line[k]
        if ch == " ":
            k, gap = k + 1, True
            continue
        if ch in "(),":
            tok = _Tok(ch, ch, k + 1, gap)
            k += 1
        elif ch == '"':
            end = line.find('"', k + 1)
            if end < 0:
                raise LineSyntaxError(line, "a String without its closing quote", k + 1)
            if end == k + 1:
                raise LineSyntaxError(line, "an empty String (6.1.4.2: at least one character)", k + 1)
            tok = _Tok("str", line[k:end + 1], k + 1, gap, line[k + 1:end])
            k = end + 1
        elif ch.isdigit() or ch in "+-.":
            text, k2 = _number(line, k)
            tok = _Tok("num", text, k + 1, gap, float(text))
            k = k2
        elif ch.isalpha():
            text, k2 = _name(line, k)
            tok = _Tok("name", text, k + 1, gap)
            k = k2
        else:
            raise LineSyntaxError(line, f"unexpected character {ch!r}", k + 1)
        if tok.gap:
            prev = toks[-1].kind if toks else None
            if prev not in (",", "(") and tok.kind not in (",", "(", ")"):
                raise LineSyntaxError(line, "illegal space (6.1.4.2: only around commas, around '(' and before ')')",
                                      tok.column - 1)
        toks.append(tok)
        gap = False
    if gap and (not toks or toks[-1].kind not in (",", "(")):
        raise LineSyntaxError(line, "illegal space at the end of the line", len(line))
    return toks


class _Parser:
    """Recursive descent over the tokens of a data, error or command body."""

    def __init__(self, line: str, toks: list[_Tok]) -> None:
        self.line, self.toks, self.pos = line, toks, 0

    def peek(self) -> _Tok | None:
        return self.toks[self.pos] if self.pos < len(self.toks) else None

    def take(self, kind: str, what: str) -> _Tok:
        tok = self.peek()
        if tok is None or tok.kind != kind:
            found = "the end of the line" if tok is None else repr(tok.text)
            col = len(self.line) if tok is None else tok.column
            raise LineSyntaxError(self.line, f"expected {what}, found {found}", col)
        self.pos += 1
        return tok

    def at(self, kind: str) -> bool:
        tok = self.peek()
        return tok is not None and tok.kind == kind

    def end(self) -> None:
        tok = self.peek()
        if tok is not None:
            raise LineSyntaxError(self.line, f"unexpected {tok.text!r} after the end of the response", tok.column)

    def separated(self, one: Callable[[], _T]) -> list[_T]:
        """one {"," one}"""
        out = [one()]
        while self.at(","):
            self.pos += 1
            out.append(one())
        return out

    def number(self) -> float:
        return float(self.take("num", "a number").value)  # type: ignore[arg-type]

    def string(self) -> str:
        return str(self.take("str", "a String").value)

    def item(self, depth: int = 0) -> Item:
        """Name "(" [arg {"," arg}] ")" with arg :== Number | String | Name | item."""
        if depth > MAX_NESTING:
            raise LineSyntaxError(self.line, "nesting too deep")
        name = self.take("name", "a name").text
        self.take("(", f"'(' after {name}")
        args: list[Arg] = []
        if not self.at(")"):
            args = self.separated(lambda: self.arg(depth))
        self.take(")", f"',' or ')' in {name}(...)")
        return Item(name, tuple(args))

    def arg(self, depth: int) -> Arg:
        tok = self.peek()
        if tok is None:
            raise LineSyntaxError(self.line, "expected an argument, found the end of the line", len(self.line))
        if tok.kind == "num":
            return self.number()
        if tok.kind == "str":
            return self.string()
        if tok.kind == "name":
            nxt = self.toks[self.pos + 1] if self.pos + 1 < len(self.toks) else None
            if nxt is not None and nxt.kind == "(":
                return self.item(depth + 1)
            self.pos += 1
            if "." in tok.text:
                raise LineSyntaxError(self.line, f"{tok.text} without '(...)'", tok.column)
            return Word(tok.text)
        raise LineSyntaxError(self.line, f"expected an argument, found {tok.text!r}", tok.column)


# ---------------------------------------------------------------------- responses


def _tag_of(line: str) -> str:
    """The tag of a line (6.2.1): 5 digits 00001..99999, or E and 4 digits (E0000 for server events)."""
    tag = line[:5]
    if not (_COMMAND_TAG.fullmatch(tag) or _EVENT_TAG.fullmatch(tag)):
        raise LineSyntaxError(line, "the first 5 characters are no tag (5 digits, or E and 4 digits)", 1)
    if tag == "00000":
        raise LineSyntaxError(line, "tag 00000 is out of range (00001..99999)", 1)
    return tag


def parse_response(line: str) -> ResponseLine:
    """Parse one response line (its CR LF removed); LineSyntaxError if it breaks the syntax of 6.1.4.2 or 6.2.2.2."""
    _check_characters(line)
    tag = _tag_of(line)
    if len(line) < 7 or line[5] != " ":
        raise LineSyntaxError(line, "no space after the tag (6.2.2.2: column 6)", 6)
    try:
        marker = Marker(line[6])
    except ValueError:
        raise LineSyntaxError(line, "the 7th character is none of & % # ! (6.2.2.2)", 7) from None
    if marker in (Marker.ACK, Marker.DONE):
        if len(line) > 7:
            raise LineSyntaxError(line, f"characters after {marker.value!r}", 8)
        if tag == SERVER_EVENT_TAG:
            raise LineSyntaxError(line, "E0000 carries server events only (6.2.1), never an ack or a completion", 1)
        return ResponseLine(line, tag, marker)
    if len(line) < 9 or line[7] != " ":
        raise LineSyntaxError(line, "no space at column 8 after the marker (6.2.2.2)", 8)
    p = _Parser(line, _tokens(line, 8))
    if marker is Marker.ERROR:
        return ResponseLine(line, tag, marker, error=_error_body(p))
    first = p.peek()
    if first is None:
        raise LineSyntaxError(line, "no data after '#'", 9)
    if first.kind == "num":
        form, values = Form.NUMBERS, tuple(p.separated(p.number))
    elif first.kind == "str":
        form, values = Form.STRINGS, tuple(p.separated(p.string))
        if len(values) > 2:
            raise LineSyntaxError(line, "more than two Strings (6.1.4.2 PropData is two)", first.column)
    elif first.kind == "(":
        p.pos += 1
        values = tuple(p.separated(p.number))
        p.take(")", "')' closing the number list")
        form = Form.VECTOR
    elif first.kind == "name":
        form, values = Form.ITEMS, tuple(p.separated(p.item))
    else:
        raise LineSyntaxError(line, f"data cannot start with {first.text!r}", first.column)
    p.end()
    return ResponseLine(line, tag, marker, form, values)


def _error_body(p: _Parser) -> ErrorReport:
    """ErrorResponse :== ... "Error" SLeftParenS F1 SCommaS F2 SCommaS F3 SCommaS Text SRightParen."""
    name = p.take("name", "Error")
    if name.text != "Error":
        raise LineSyntaxError(p.line, f"an error response names {name.text!r}, not Error", name.column)
    p.take("(", "'(' after Error")
    f1 = p.take("num", "the severity F1")
    if not re.fullmatch(r"[0-9]", f1.text):
        raise LineSyntaxError(p.line, "the severity F1 must be one digit", f1.column)
    p.take(",", "',' after F1")
    f2 = p.take("num", "the error number F2")
    if not re.fullmatch(r"[0-9]{4}", f2.text):
        raise LineSyntaxError(p.line, "the error number F2 must be four digits", f2.column)
    p.take(",", "',' after F2")
    tok = p.peek()
    if tok is not None and tok.kind == "name" and "." not in tok.text:
        p.pos += 1
        method, quoted = tok.text, False
    else:
        method, quoted = p.string(), True
    p.take(",", "',' after F3")
    text = p.string()
    p.take(")", "')' closing Error(...)")
    p.end()
    return ErrorReport(int(f1.text), int(f2.text), method, text, quoted)


# ---------------------------------------------------------------------- commands


def check_command(line: str) -> None:
    """The syntax of a command line (6.1.4.2 Command, 6.2.1, 6.2.2.1); LineSyntaxError if broken. An E-tag carries
    only the methods of the fast queue (names ending in E, 6.2.1), and those always carry one."""
    _check_characters(line)
    tag = _tag_of(line)
    if tag == SERVER_EVENT_TAG:
        raise LineSyntaxError(line, "E0000 is the server's own tag (6.2.1)", 1)
    if len(line) < 7 or line[5] != " ":
        raise LineSyntaxError(line, "no space after the tag (6.2.2.1: column 6)", 6)
    p = _Parser(line, _tokens(line, 6))
    first = p.peek()
    if first is None or first.kind != "name" or "." in first.text:
        raise LineSyntaxError(line, "a command is a method name (a BasicName) and its arguments", 7)
    name = first.text
    p.pos += 1
    p.take("(", f"'(' after {name}")
    if not p.at(")"):
        p.separated(lambda: _command_arg(p))
    p.take(")", f"',' or ')' in {name}(...)")
    p.end()
    if tag.startswith("E") and name not in EVENT_METHODS:
        raise LineSyntaxError(line, f"only fast-queue methods (ending in E) may carry an E-tag, not {name}", 1)
    if name in EVENT_METHODS and not tag.startswith("E"):
        raise LineSyntaxError(line, f"{name} is a fast-queue method: it carries an E-tag (6.2.1)", 1)


def _command_arg(p: _Parser) -> None:
    """Argument :== String | Number | Property | ETag | BasicName; Property :== Name "(" [Number {"," Number}] ")"."""
    tok = p.peek()
    if tok is not None and tok.kind == "name":
        nxt = p.toks[p.pos + 1] if p.pos + 1 < len(p.toks) else None
        p.pos += 1
        if nxt is None or nxt.kind != "(":
            if "." in tok.text:
                raise LineSyntaxError(p.line, f"{tok.text} without '(...)'", tok.column)
            return
        p.pos += 1
        if not p.at(")"):
            p.separated(p.number)
        p.take(")", f"',' or ')' in {tok.text}(...) (a property's arguments are numbers)")
        return
    if tok is not None and tok.kind == "str":
        p.pos += 1
        return
    p.number()


def format_number(value: float, decimals: int = 6) -> str:
    """A Number (6.1.4.2) with this many decimals, trailing zeros kept off; ValueError beyond 16 digits."""
    v = float(value)
    if v != v or v in (float("inf"), float("-inf")):
        raise ValueError(f"not a finite number: {value!r}")
    text = f"{v:.{decimals}f}".rstrip("0").rstrip(".") if decimals else f"{v:.0f}"
    if text in ("-0", ""):
        text = "0"
    if sum(ch.isdigit() for ch in text.lstrip("+-").split("e")[0]) > MAX_NUMBER_DIGITS:
        raise ValueError(f"{value!r} needs more than {MAX_NUMBER_DIGITS} digits")
    return text


def format_arg(arg: Arg) -> str:
    """One argument as on the wire: a Number, a quoted String, a bare name or an item."""
    if isinstance(arg, Word | Item):
        return str(arg)
    if isinstance(arg, str):
        if not arg or '"' in arg or any(not PRINTABLE_MIN <= ord(c) <= PRINTABLE_MAX for c in arg):
            raise ValueError(f"not a String of 6.1.4.2 (1 or more printable characters, no quote): {arg!r}")
        return f'"{arg}"'
    return format_number(arg)


def command_line(tag: str, method: str, *args: Arg) -> str:
    """``TAG Method(args)``, checked (``check_command``) before it is returned."""
    line = f"{tag} {method}({', '.join(format_arg(a) for a in args)})"
    check_command(line)
    return line


def format_tag(number: int, event: bool = False) -> str:
    """A command tag 00001..99999 or an E-tag E0001..E9999 (6.2.1)."""
    if event:
        if not 1 <= number <= 9999:
            raise ValueError(f"an E-tag is E0001..E9999, not {number}")
        return f"E{number:04d}"
    if not TAG_MIN <= number <= TAG_MAX:
        raise ValueError(f"a command tag is 00001..99999, not {number}")
    return f"{number:05d}"
