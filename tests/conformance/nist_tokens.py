"""Lexical level of the NIST-mirroring validators: optional spaces, numbers, strings, keywords (6.1.4.2).

Test support code. A line is first freed of its optional spaces (``unspace``: spaces may stand only before or after
a comma or a parenthesis, or inside a string), then cut into items. Response items: ``(`` ``)`` ``,`` ``.`` and
``n`` (number), ``s`` (string), ``k`` (keyword). Command items are read as NIST's command parser reads them: ``,``
``.``, ``e`` (empty parentheses), ``p`` (one number in parentheses), ``j`` (the three numbers of ``IJK(i,j,k)``),
``n``, ``s``, ``k`` and ``t`` (an event tag argument). A ``Tokens`` holds the kinds as one string (its *shape*) and
the values beside it, so that the forms can be checked with patterns over the shape. An empty string ``""`` is
refused in responses too (6.1.4.2: ``String :== q Char {Char} q``), where NIST's response parser lets it pass.
"""

from __future__ import annotations

from dataclasses import dataclass


class Fail(Exception):
    """A check failed; ``message`` in NIST's words."""

    def __init__(self, message: str) -> None:
        super().__init__(message)
        self.message = message


RESPONSE_KEYWORDS = frozenset({
    "Accel", "Act", "Alignment", "Approach", "A", "B", "CenterPart", "ChangeToolAction", "ChangeTool",
    "CollisionVolume", "CoordSystem", "C", "Def", "DMEVersion", "ER", "Error", "ErrStatus", "FoundTool",
    "GetCsyTransformation", "GetMachineClass", "GoToPar", "GoTo", "Id", "IJK", "IsHomed", "IsUserEnabled",
    "JogDisplayCsy", "JogMoveCsy", "KeyPress", "MachineCsy", "Max", "Min", "MoveableMachineCsy", "MoveAuto", "MoveMan",
    "MultipleArmCsy", "Name", "OBB", "PartCsy", "Phi", "PtMeasPar", "PtMeas", "Q", "Retract", "Rotate", "R", "Search",
    "SensorCsy", "SetProp", "Speed", "Switch", "TiltCenterPart", "TiltPart", "Tool", "X", "Y", "Z",
})
"""The words NIST's response parser knows (``parserRes::parseKeyword``)."""
RESPONSE_KEYWORDS_1_4_3 = frozenset({"CartCMM", "CartCMMWithRotaryTable", "AvrRadius"})
"""Words of 1.4.3 forms NIST's parser does not know (6.3.2.8 enumeration, 6.3.13)."""
COMMAND_KEYWORDS = frozenset({
    "Accel", "Act", "Alignment", "Approach", "A", "B", "CollisionVolume", "C", "Def", "Dis", "ER", "FoundTool",
    "GoToPar", "Id", "IJK", "JogDisplayCsy", "JogMoveCsy", "MachineCsy", "Max", "Min", "MoveableMachineCsy", "MoveAuto",
    "MoveMan", "MultipleArmCsy", "Name", "OBB", "PartCsy", "Phi", "PtMeasPar", "Q", "Retract", "Rotate", "R", "Search",
    "SensorCsy", "Speed", "Switch", "Time", "Tool", "X", "Y", "Z",
})
"""The words NIST's command parser knows (``parserCmd::parseKeyword``)."""
COMMAND_KEYWORDS_1_4_3 = frozenset({"AvrRadius"})


def unspace(line: str, start: int) -> str:
    """The line without its optional spaces from ``start`` on; ILLEGAL SPACE where a space may not stand."""
    out = [line[:start]]
    stringing = space_before = punct_before = False
    for c in [*line[start:], ""]:
        if stringing:
            stringing = c != '"'
        elif c == " ":
            if not punct_before:
                space_before = True
            continue
        elif space_before:
            if c not in ("(", ")", ","):
                raise Fail("ILLEGAL SPACE")
            space_before, punct_before = False, True
        elif c in ("(", ")", ","):
            punct_before = True
        else:
            punct_before = False
            stringing = c == '"'
        out.append(c)
    return "".join(out)


def _is_digit(c: str) -> bool:
    return "0" <= c <= "9"


def read_number(text: str, i: int) -> tuple[float, int]:
    """The number starting at ``text[i]`` and the index of its last character."""
    k = i + (1 if text[i] in "+-" else 0)
    start, dot = k, 0
    while k < len(text) and (text[k] == "." or _is_digit(text[k])):
        if text[k] == ".":
            if dot:
                raise Fail("BAD NUMBER TWO DECIMAL POINTS")
            dot = 1
        k += 1
    digits = k - start - dot
    if digits == 0:
        raise Fail("BAD NUMBER NO DIGITS")
    if digits > 16:
        raise Fail("BAD NUMBER MORE THAN 16 DIGITS")
    if k < len(text) and text[k] in "Ee":
        k += 1
        if k < len(text) and text[k] in "+-":
            k += 1
        j = 0
        while k < len(text) and _is_digit(text[k]):
            k, j = k + 1, j + 1
        if not 1 <= j <= 3:
            raise Fail("BAD E NUMBER EXPONENT MUST HAVE ONE TWO OR THREE DIGITS")
    return float(text[i:k]), k - 1


def read_string(text: str, i: int, allow_empty: bool) -> tuple[str, int]:
    """The string whose opening quote is ``text[i]`` and the index of its closing quote."""
    j = i + 1
    while j < len(text) and text[j] != '"':
        if not " " <= text[j] <= "~":
            raise Fail("BAD STRING")
        j += 1
    if j >= len(text) or (j == i + 1 and not allow_empty):
        raise Fail("BAD STRING")
    return text[i + 1 : j], j


def read_keyword(text: str, i: int, words: frozenset[str]) -> tuple[str, int]:
    """The known keyword starting at ``text[i]`` and the index of its last character; what follows it must be a dot,
    a comma or a parenthesis."""
    j = i
    while j < len(text) and (text[j].isascii() and text[j].isalnum()):
        j += 1
    name = text[i:j]
    found = max((w for w in words if name.startswith(w)), key=len, default=None)
    if found is None:
        raise Fail("BAD KEYWORD")
    end = i + len(found)
    if end >= len(text) or text[end] not in ".,()":
        raise Fail("BAD CHARACTER AFTER KEYWORD")
    return found, end - 1


@dataclass
class Tokens:
    """Items as a shape string (one character per item) and their values."""

    items: list[tuple[str, object]]

    @property
    def shape(self) -> str:
        return "".join(kind for kind, _ in self.items)

    def __len__(self) -> int:
        return len(self.items)

    def kind(self, i: int) -> str:
        return self.items[i][0] if 0 <= i < len(self.items) else ""

    def value(self, i: int) -> object:
        return self.items[i][1] if 0 <= i < len(self.items) else None

    def word(self, i: int) -> str:
        """The keyword at ``i`` ('' if the item is no keyword)."""
        return str(self.items[i][1]) if self.kind(i) == "k" else ""

    def number(self, i: int) -> float:
        value = self.value(i)
        return float(value) if isinstance(value, float) else float("nan")


def tokenize_response(text: str) -> Tokens:
    """The items of an unspaced response line from its ninth character to its end."""
    words = RESPONSE_KEYWORDS | RESPONSE_KEYWORDS_1_4_3
    items: list[tuple[str, object]] = []
    i = 8
    while i < len(text) and text[i] != "\r":
        c, d = text[i], text[i + 1 : i + 2]
        if c in "(),":
            items.append((c, c))
        elif c == '"':
            value, i = read_string(text, i, allow_empty=False)  # 6.1.4.2: String :== q Char {Char} q
            items.append(("s", value))
        elif c == "." and "A" <= d <= "Z":
            items.append((".", "."))
        elif c in "+-." or _is_digit(c):
            number, i = read_number(text, i)
            items.append(("n", number))
        elif "A" <= c <= "Z":
            word, i = read_keyword(text, i, words)
            items.append(("k", word))
        else:
            raise Fail("BAD RESPONSE ITEMS")
        i += 1
    if text[i:]:
        raise Fail("BAD CHARACTER AFTER RESPONSE END")
    return Tokens(items)


def tokenize_command(text: str, i: int) -> tuple[list[tuple[str, object]], int]:
    """The argument items of an unspaced command line from ``i`` (after the method's ``(``) up to its ``)``, and the
    index after that ``)``."""
    words = COMMAND_KEYWORDS | COMMAND_KEYWORDS_1_4_3
    items: list[tuple[str, object]] = []
    while True:
        if i >= len(text):
            raise Fail("BAD COMMAND ARGUMENTS")
        c, d = text[i], text[i + 1 : i + 2]
        if c == ")":
            return items, i + 1
        if c == ",":
            items.append((",", ","))
        elif c == "." and "A" <= d <= "Z":
            items.append((".", "."))
        elif c == "(" and d == ")":
            items.append(("e", "()"))
            i += 1
        elif c == "(" and d and (d in "+-." or _is_digit(d)):
            if items and items[-1] == ("k", "IJK"):
                value, i = _read_ijk(text, i + 1)
                items.append(("j", value))
            else:
                number, i = read_number(text, i + 1)
                if text[i + 1 : i + 2] != ")":
                    raise Fail("BAD COMMAND ARGUMENTS")
                items.append(("p", number))
                i += 1
        elif c == '"':
            value, i = read_string(text, i, allow_empty=False)
            items.append(("s", value))
        elif c in "+-." or _is_digit(c):
            number, i = read_number(text, i)
            items.append(("n", number))
        elif c == "E" and len(text) > i + 4 and all(_is_digit(x) for x in text[i + 1 : i + 5]):
            if text[i + 5 : i + 6] not in (".", ",", "(", ")") or i + 5 >= len(text):
                raise Fail("BAD CHARACTER AFTER KEYWORD")
            items.append(("t", int(text[i + 1 : i + 5])))
            i += 4
        elif "A" <= c <= "Z":
            word, i = read_keyword(text, i, words)
            items.append(("k", word))
        else:
            raise Fail("BAD COMMAND ARGUMENTS")
        i += 1


def _read_ijk(text: str, i: int) -> tuple[tuple[float, float, float], int]:
    values: list[float] = []
    for n in range(3):
        if n:
            i += 1
            if text[i : i + 1] != ",":
                raise Fail("BAD IJK NUMBERS")
            i += 1
        if not text[i : i + 1] or not (text[i] in "+-." or _is_digit(text[i])):
            raise Fail("BAD IJK NUMBERS")
        value, i = read_number(text, i)
        values.append(value)
    i += 1
    if text[i : i + 1] != ")":
        raise Fail("BAD IJK NUMBERS")
    return (values[0], values[1], values[2]), i
