"""The command forms NIST's command parser checks, per method (test support code for ``nist_grammar``).

``check_arguments(name, items, notes)`` raises ``Fail(<NIST's message>)`` for arguments the method does not take;
``IPP_ERRORS`` maps each message to the I++ error number NIST's parser assigns to it (``parserCmd::getIppErr``).
Items are those of ``nist_tokens.tokenize_command`` (``e`` = ``()``, ``p`` = ``(number)``, ``j`` = IJK's numbers).
"""

from __future__ import annotations

from tests.conformance.nist_tokens import Fail, Tokens

NO_ARGUMENT = frozenset({
    "AbortE", "ClearAllErrors", "DisableUser", "EnableUser", "EndSession", "EnumTools", "GetCoordSystem",
    "GetDMEVersion", "GetErrStatusE", "GetMachineClass", "GetXtdErrStatus", "Home", "IsHomed", "IsUserEnabled",
    "ReQualify", "StartSession", "StopAllDaemons",
})
ONE_STRING = frozenset({"ChangeTool", "FindTool", "SetTool", "GetChangeToolAction"})
NUMBER_LISTS = {
    "AlignPart": ((7, 14), "MUST HAVE 7 OR 14 ARGUMENTS"), "AlignTool": ((4, 8), "MUST HAVE 4 OR 8 ARGUMENTS"),
    "CenterPart": ((4,), "MUST HAVE 4 ARGUMENTS"), "TiltPart": ((4,), "MUST HAVE 4 ARGUMENTS"),
    "TiltCenterPart": ((7,), "MUST HAVE 7 ARGUMENTS"),
}
SCANS = {
    "ScanInCylEndIsPlane": (26, {30: "stepw", 44: "through"}, (30, 44, 50)),
    "ScanInCylEndIsSphere": (23, {30: "stepw", 38: "diameter"}, (30, 38, 44)),
    "ScanInPlaneEndIsCyl": (21, {18: "stepw", 32: "diameter", 34: "through"}, (18, 32, 34, 40)),
    "ScanInPlaneEndIsPlane": (20, {18: "stepw", 32: "through"}, (18, 32, 38)),
    "ScanInPlaneEndIsSphere": (17, {18: "stepw", 26: "diameter"}, (18, 26, 32)),
    "ScanOnCircle": (12, {}, (22,)),
    "ScanOnLine": (10, {18: "stepw"}, (18,)),
}
"""Scans: number of arguments, the checks on some items (item index: rule), the items that must be numbers."""
EVENT_COMMANDS = frozenset({"AbortE", "GetErrStatusE", "GetPropE", "OnMoveReportE"})
CSY_TRANSFORMATIONS = ("JogDisplayCsy", "JogMoveCsy", "MoveableMachineCsy", "MultipleArmCsy", "PartCsy", "SensorCsy")
COORD_SYSTEMS = ("MachineCsy", "MultipleArmCsy", "PartCsy", "MoveableMachineCsy")
GOTO_PARS = ("Speed", "Accel")
PTMEAS_PARS = ("Speed", "Accel", "Approach", "Retract", "Search")
PARAMETER_PARTS = ("Act", "Def", "Max", "Min")
COMMANDS = (*NO_ARGUMENT, *ONE_STRING, *NUMBER_LISTS, *SCANS, "EnumAllProp", "EnumProp", "Get", "GetCsyTransformation",
            "GetErrorInfo", "GetProp", "GetPropE", "GoTo", "LockAxis", "OnMoveReportE", "OnPtMeasReport",
            "OnScanReport", "PtMeas", "ScanOnCircleHint", "ScanOnLineHint", "ScanUnknownHint", "SetCoordSystem",
            "SetCsyTransformation", "SetProp", "StopDaemon")
"""The 55 methods NIST's command parser knows."""
NOTE_AVR_RADIUS = "1.4.3: Tool.AvrRadius() (6.3.13)"
NOTE_Q = "1.4.3: Q() in OnPtMeasReport and its reports (6.3.2.6, 6.3.2.24)"

_509 = ("ARGUMENT FIRST PART MUST BE TOOL OR FOUNDTOOL", "ARGUMENT FOURTH PART MUST BE ACT", "ARGUMENT FOURTH PART BAD",
        "ARGUMENT MUST BE A NUMBER", "ARGUMENT MUST BE EVENT TAG", "ARGUMENT MUST BE INTEGER",
        "ARGUMENT MUST BE POSITIVE", "ARGUMENT MUST BE STRING", "ARGUMENT MUST END WITH EMPTY PARENTHESES",
        "ARGUMENT MUST END WITH NUMBER IN PARENTHESES", "ARGUMENT SECOND PART BAD",
        "ARGUMENT SECOND PART MUST BE GOTOPAR OR PTMEASPAR", "ARGUMENT THIRD PART BAD",
        "BAD E NUMBER EXPONENT MUST HAVE ONE TWO OR THREE DIGITS", "BAD FIRST ARGUMENT",
        "BAD NUMBER MORE THAN 16 DIGITS", "BAD NUMBER NO DIGITS", "BAD NUMBER OF THROUGHS",
        "BAD NUMBER TWO DECIMAL POINTS", "BAD STRING", "DIAMETER MUST BE POSITIVE",
        "DIS MUST BE FOLLOWED BY NUMBER IN PARENS", "NUMBER THROUGH MUST BE INTEGER", "NUMBER THROUGH MUST BE POSITIVE",
        "STEPW MUST BE POSITIVE", "TIME MUST BE FOLLOWED BY NUMBER IN PARENS", "X NOT FOLLOWED BY NUMBER IN PARENS",
        "Y NOT FOLLOWED BY NUMBER IN PARENS", "Z NOT FOLLOWED BY NUMBER IN PARENS")
_502 = ("BAD ARGUMENTS", "BAD CHARACTER AFTER KEYWORD", "BAD COMMAND ARGUMENTS", "BAD DOTS", "BAD IJK NUMBERS",
        "BAD KEYWORD", "IJK NOT FOLLOWED BY ARGIJK", "ILLEGAL SPACE", "MUST HAVE NO ARGUMENTS",
        "MUST HAVE ONE ARGUMENT",
        "MUST HAVE 4 ARGUMENTS", "MUST HAVE 4 OR 8 ARGUMENTS", "MUST HAVE 7 ARGUMENTS", "MUST HAVE 7 OR 14 ARGUMENTS",
        "X Y Z ALL MISSING",
        *(f"{item} ARGUMENT USED TWICE" for item in ("C", "DIS", "ER", "IJK", "PHI", "Q", "R", "TIME", "TOOL A",
                                                      "TOOL B", "TOOL C", "X", "Y", "Z")))
IPP_ERRORS: dict[str, int] = {
    **dict.fromkeys(_509, 509), **dict.fromkeys(_502, 502),
    "BAD CHARACTER AFTER COMMAND END": 507, "BAD COMMAND NAME": 507, "SPACE MISSING AFTER TAG": 2,
    "BAD TAG CHARACTER": 1, "EVENT COMMAND MUST HAVE EVENT TAG": 1, "NON EVENT COMMAND MUST NOT HAVE EVENT TAG": 1,
    "TAG NUMBER OUT OF RANGE FOR EVENT TAG": 1, "TAG NUMBER OUT OF RANGE FOR COMMAND TAG": 1,
    "THETA OUT OF RANGE": 1007,
}
"""NIST's command parser's message -> I++ error number."""


def command_name(text: str) -> tuple[str, int]:
    """The method an unspaced command line calls, and the index after its ``(``."""
    for name in COMMANDS:
        if text.startswith(f"{name}(", 6):
            return name, 7 + len(name)
    raise Fail("BAD COMMAND NAME")


def _twice(item: str) -> Fail:
    return Fail(f"{item.upper().replace('TOOL.', 'TOOL ')} ARGUMENT USED TWICE")


def check_arguments(name: str, t: Tokens, notes: list[str]) -> None:
    """The argument rules of method ``name`` (``parserCmd::makeXXX``)."""
    count = len(t)
    if name in NO_ARGUMENT:
        if count:
            raise Fail("MUST HAVE NO ARGUMENTS")
    elif name in ONE_STRING:
        _one(t, "s", "ARGUMENT MUST BE STRING")
    elif name in NUMBER_LISTS:
        numbers, message = NUMBER_LISTS[name]
        if count not in tuple(2 * k - 1 for k in numbers):
            raise Fail(message)
        if t.shape != "n" + ",n" * (count // 2):
            raise Fail("BAD ARGUMENTS")
    elif name in SCANS:
        _scan(name, t)
    elif name in ("ScanOnCircleHint", "ScanOnLineHint"):
        if t.shape != "n,n" or t.number(0) < 0 or t.number(2) < 0:
            raise Fail("BAD ARGUMENTS")
    elif name == "ScanUnknownHint":
        _one(t, "n", "ARGUMENT MUST BE A NUMBER")
        if t.number(0) <= 0:
            raise Fail("ARGUMENT MUST BE POSITIVE")
    elif name in ("EnumProp", "EnumAllProp"):
        _enum_prop(t)
    elif name in ("GetProp", "GetPropE"):
        _get_prop(t, notes)
    elif name == "SetProp":
        _set_prop(t)
    elif name == "PtMeas":
        _pt_meas(t)
    elif name in ("Get", "GoTo", "LockAxis", "OnMoveReportE", "OnPtMeasReport", "OnScanReport"):
        _item_list(name, t, notes)
    elif name == "GetCsyTransformation":
        _one(t, "k", "BAD ARGUMENTS")
        if t.word(0) not in CSY_TRANSFORMATIONS:
            raise Fail("BAD ARGUMENTS")
    elif name == "SetCoordSystem":
        _one(t, "k", "BAD ARGUMENTS")
        if t.word(0) not in COORD_SYSTEMS:
            raise Fail("BAD ARGUMENTS")
    elif name == "SetCsyTransformation":
        if count != 13:
            raise Fail("MUST HAVE 7 ARGUMENTS")
        if t.shape != "k" + ",n" * 6:
            raise Fail("BAD ARGUMENTS")
        if t.word(0) not in CSY_TRANSFORMATIONS:
            raise Fail("BAD FIRST ARGUMENT")
        if not 0 <= t.number(8) <= 180:
            raise Fail("THETA OUT OF RANGE")
    elif name == "GetErrorInfo":
        _one(t, "n", "ARGUMENT MUST BE INTEGER")
        if t.number(0) != int(t.number(0)):
            raise Fail("ARGUMENT MUST BE INTEGER")
    elif name == "StopDaemon":
        _one(t, "t", "ARGUMENT MUST BE EVENT TAG")


def _one(t: Tokens, kind: str, message: str) -> None:
    if len(t) != 1:
        raise Fail("MUST HAVE ONE ARGUMENT")
    if t.kind(0) != kind:
        raise Fail(message)


def _scan(name: str, t: Tokens) -> None:
    arguments, rules, numbers = SCANS[name]
    if len(t) != 2 * arguments - 1 or any(t.kind(i) != "n" for i in numbers):
        raise Fail("BAD ARGUMENTS")
    for index, rule in rules.items():
        value = t.number(index)
        if rule == "stepw" and value <= 0:
            raise Fail("STEPW MUST BE POSITIVE")
        if rule == "diameter" and value <= 0:
            raise Fail("DIAMETER MUST BE POSITIVE")
        if rule == "through" and value <= 0:
            raise Fail("NUMBER THROUGH MUST BE POSITIVE")
        if rule == "through" and value != int(value):
            raise Fail("NUMBER THROUGH MUST BE INTEGER")
    if t.shape != "n" + ",n" * (arguments - 1):
        raise Fail("BAD ARGUMENTS")


def _enum_prop(t: Tokens) -> None:
    count = len(t)
    if count not in (2, 4, 6, 8):
        raise Fail("BAD ARGUMENTS")
    if t.word(0) not in ("Tool", "FoundTool"):
        raise Fail("ARGUMENT FIRST PART MUST BE TOOL OR FOUNDTOOL")
    if t.kind(count - 1) != "e":
        raise Fail("ARGUMENT MUST END WITH EMPTY PARENTHESES")
    if any(t.kind(i) != "." for i in (1, 3, 5) if i < count - 1):
        raise Fail("BAD DOTS")
    if count > 2 and t.word(2) not in ("GoToPar", "PtMeasPar"):
        raise Fail("ARGUMENT SECOND PART MUST BE GOTOPAR OR PTMEASPAR")
    if count > 4 and t.word(4) not in (GOTO_PARS if t.word(2) == "GoToPar" else PTMEAS_PARS):
        raise Fail("ARGUMENT THIRD PART BAD")
    if count > 6 and t.word(6) not in PARAMETER_PARTS:
        raise Fail("ARGUMENT FOURTH PART BAD")


def _get_prop(t: Tokens, notes: list[str]) -> None:
    n, count = 0, len(t)
    while n < count:
        if count < n + 4:
            raise Fail("BAD ARGUMENTS")
        if t.word(n) not in ("Tool", "FoundTool"):
            raise Fail("ARGUMENT FIRST PART MUST BE TOOL OR FOUNDTOOL")
        if t.kind(n + 1) != ".":
            raise Fail("BAD DOTS")
        if t.kind(n + 2) != "k":
            raise Fail("ARGUMENT SECOND PART BAD")
        key1, key2 = t.word(n), t.word(n + 2)
        if t.kind(n + 3) == "e":
            if key1 == "FoundTool" and key2 in ("Alignment", "CollisionVolume"):
                raise Fail("BAD ARGUMENTS")
            if key2 == "AvrRadius" and key1 == "Tool":
                notes.append(NOTE_AVR_RADIUS)
            elif key2 not in ("Alignment", "CollisionVolume", "Name", "Id"):
                raise Fail("ARGUMENT SECOND PART BAD")
            n += 4
        elif key2 not in ("GoToPar", "PtMeasPar"):
            raise Fail("ARGUMENT SECOND PART BAD")
        elif t.kind(n + 3) != ".":
            raise Fail("BAD DOTS")
        elif count < n + 6:
            raise Fail("BAD ARGUMENTS")
        elif t.word(n + 4) not in (GOTO_PARS if key2 == "GoToPar" else PTMEAS_PARS):
            raise Fail("ARGUMENT THIRD PART BAD")
        elif t.kind(n + 5) == "e":
            n += 6
        elif t.kind(n + 5) != ".":
            raise Fail("BAD DOTS")
        elif count < n + 8:
            raise Fail("BAD ARGUMENTS")
        elif t.kind(n + 7) == "e":
            if t.word(n + 6) not in PARAMETER_PARTS:
                raise Fail("ARGUMENT FOURTH PART BAD")
            n += 8
        else:
            raise Fail("ARGUMENT MUST END WITH EMPTY PARENTHESES")
        if n != count and t.kind(n) != ",":
            raise Fail("BAD ARGUMENTS")
        n += 1


def _set_prop(t: Tokens) -> None:
    n, count = 0, len(t)
    while n < count:
        if count < n + 6:
            raise Fail("BAD ARGUMENTS")
        if t.word(n) not in ("Tool", "FoundTool"):
            raise Fail("ARGUMENT FIRST PART MUST BE TOOL OR FOUNDTOOL")
        if t.kind(n + 1) != "." or t.kind(n + 3) != ".":
            raise Fail("BAD DOTS")
        key2 = t.word(n + 2)
        if key2 not in ("GoToPar", "PtMeasPar"):
            raise Fail("ARGUMENT SECOND PART MUST BE GOTOPAR OR PTMEASPAR")
        if t.word(n + 4) not in (GOTO_PARS if key2 == "GoToPar" else PTMEAS_PARS):
            raise Fail("ARGUMENT THIRD PART BAD")
        if t.kind(n + 5) == "p":
            n += 6
        elif t.kind(n + 5) != ".":
            raise Fail("BAD DOTS")
        elif count < n + 8:
            raise Fail("BAD ARGUMENTS")
        elif t.kind(n + 7) == "p":
            if t.word(n + 6) != "Act":
                raise Fail("ARGUMENT FOURTH PART MUST BE ACT")
            n += 8
        else:
            raise Fail("ARGUMENT MUST END WITH NUMBER IN PARENTHESES")
        if n != count and t.kind(n) != ",":
            raise Fail("BAD ARGUMENTS")
        n += 1


def _pt_meas(t: Tokens) -> None:
    count = len(t)
    if count not in (2, 5, 8, 11):
        raise Fail("BAD ARGUMENTS")
    seen: set[str] = set()
    for n in range(0, count, 3):
        if t.kind(n) != "k" or (n + 2 < count and t.kind(n + 2) != ","):
            raise Fail("BAD ARGUMENTS")
        word = t.word(n)
        if word in ("X", "Y", "Z"):
            if t.kind(n + 1) != "p":
                raise Fail(f"{word} NOT FOLLOWED BY NUMBER IN PARENS")
        elif word == "IJK":
            if t.kind(n + 1) != "j":
                raise Fail("IJK NOT FOLLOWED BY ARGIJK")
        else:
            continue
        if word in seen:
            raise _twice(word)
        seen.add(word)
    if not seen & {"X", "Y", "Z"}:
        raise Fail("X Y Z ALL MISSING")


ITEM_LISTS = {
    # method: (items reported alone, whether a Tool.<x> other than A, B, C is refused, parentheses, least items)
    "Get": (("R", "X", "Y", "Z"), True, "e", 2),
    "GoTo": (("X", "Y", "Z"), False, "p", 2),
    "OnMoveReportE": (("R", "X", "Y", "Z"), False, "e", 0),
    "OnPtMeasReport": (("ER", "IJK", "R", "X", "Y", "Z", "Q"), True, "e", 2),
    "OnScanReport": (("ER", "IJK", "Q", "R", "X", "Y", "Z"), True, "e", 2),
    "LockAxis": (("C", "Phi", "R", "X", "Y", "Z"), True, "e", 2),
}


def _item_list(name: str, t: Tokens, notes: list[str]) -> None:
    """Get, GoTo, LockAxis and the On...Report methods: a comma-separated list of items, each at most once."""
    singles, strict_tool, paren, least = ITEM_LISTS[name]
    count, n = len(t), 0
    seen: set[str] = set()
    if count < least:
        raise Fail("BAD ARGUMENTS")
    while n < count:
        word = t.word(n)
        if not word or n + 1 == count:
            raise Fail("BAD ARGUMENTS")
        if name == "OnMoveReportE" and word in ("Dis", "Time"):
            if t.kind(n + 1) != "p":
                raise Fail(f"{word.upper()} MUST BE FOLLOWED BY NUMBER IN PARENS")
            if word in seen:
                raise _twice(word)
            seen.add(word)
            n += 3
            continue
        if word in singles and name != "LockAxis":
            if t.kind(n + 1) != paren or not _list_end(t, n + 2):
                raise Fail("BAD ARGUMENTS")
            if word == "Q" and name == "OnPtMeasReport":
                notes.append(NOTE_Q)
            item, n = word, n + 3
        elif word == "Tool" and name != "LockAxis":
            if n + 3 >= count or t.shape[n + 1 : n + 4] != f".k{paren}" or not _list_end(t, n + 4):
                raise Fail("BAD ARGUMENTS")
            axis = t.word(n + 2)
            n += 5
            if axis not in ("A", "B", "C"):
                if strict_tool:
                    raise Fail("BAD ARGUMENTS")
                continue
            item = f"Tool.{axis}"
        elif name == "LockAxis":
            if t.kind(n + 1) != "e" or not _list_end(t, n + 2) or word not in singles:
                raise Fail("BAD ARGUMENTS")
            item, n = word, n + 3
        else:
            raise Fail("BAD ARGUMENTS")
        if item in seen:
            raise _twice(item)
        seen.add(item)


def _list_end(t: Tokens, at: int) -> bool:
    """After an item: the end, or a comma followed by more."""
    return at >= len(t) or (t.kind(at) == "," and at + 1 < len(t))

