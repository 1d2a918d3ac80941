"""The response forms NIST's response parser checks, per response (test support code for ``nist_grammar``).

Each check gets the items of one response (``nist_tokens.Tokens``) and, where NIST looks at fixed columns (a
one-digit severity, a four-digit error number, a one-character boolean), the unspaced line. A failure raises
``Fail("<Response name>: <NIST's message>")``; a 1.4.3 form NIST does not know is accepted and noted.
"""

from __future__ import annotations

from tests.conformance.nist_tokens import Fail, Tokens

NIST_ERRORS: dict[int, tuple[str, str]] = {
    0: ("0", "Buffer full"), 1: ("2", "Illegal tag"), 2: ("2", "No space at pos. 6"), 3: ("2", "Reserved"),
    4: ("2", "Reserved"), 5: ("2", "Reserved"), 6: ("2", "Transaction aborted (Use ClearAllErrors to Continue)"),
    7: ("3", "Illegal character"), 8: ("3", "Protocol error"), 500: ("3", "Emergency stop"),
    501: ("3", "Unsupported command"), 502: ("3", "Incorrect arguments"),
    503: ("9", "Controller communications failure"), 504: ("1", "Argument out of range"),
    505: ("3", "Argument not recognized"), 506: ("3", "Argument not supported"), 507: ("3", "Illegal command"),
    508: ("3", "Bad context"), 509: ("3", "Bad argument"), 510: ("3", "Bad property"),
    511: ("3", "Error processing method"), 512: ("1", "No daemons are active"), 513: ("2", "Daemon does not exist"),
    514: ("2", "Use ClearAllErrors to continue"), 515: ("2", "Daemon already exists"),
    1000: ("3", "Machine in error state"), 1001: ("2", "Illegal touch"), 1002: ("9", "Axis does not exist"),
    1003: ("2", "No touch"), 1004: ("9", "Number of angles not supported on current device"),
    1005: ("3", "Error during home"), 1006: ("2", "Surface not found"), 1007: ("3", "Theta out of range"),
    1008: ("3", "Target position out of machine volume"), 1009: ("3", "Air pressure out of range"),
    1010: ("2", "Vector has no norm"), 1500: ("3", "Failed to re-seat head"), 1501: ("3", "Probe not armed"),
    1502: ("3", "Tool not found"), 1503: ("3", "Tool not defined"), 2000: ("3", "Tool not calibrated"),
    2001: ("2", "Head error excessive force"), 2002: ("3", "Type of probe does not allow this operation"),
    2500: ("3", "Machine limit encountered [Move Out Of Limits]"), 2501: ("3", "Axis not active"),
    2502: ("3", "Axis position error"), 2503: ("9", "Scale read head failure"), 2504: ("3", "Collision"),
    2505: ("2", "Specified angle out of range"), 2506: ("2", "Part not aligned"),
}
"""NIST's error table (``IppCmdRes.h``, severities and texts as of 1.40): code -> (severity, text)."""
ERRORS_1_4_3: dict[int, tuple[str, str]] = {1011: ("2", "Unable to move"), 1012: ("2", "Bad lock combinations")}
"""Errors 8.2 of 1.4.3 defines that NIST's table lacks."""
TEXT_0006_1_4_3 = "Transaction aborted (Use ClearAllErrors To Continue)"

NOTE_MACHINE_CLASS = "1.4.3: GetMachineClass answers an enumeration, not a string (6.3.2.8)"
NOTE_0006 = "1.4.3: error 0006 reads 'Transaction aborted (Use ClearAllErrors To Continue)' (8.2)"
NOTE_AVR_RADIUS = "1.4.3: Tool.AvrRadius() (6.3.13)"
NOTE_Q = "1.4.3: Q() in OnPtMeasReport and its reports (6.3.2.6, 6.3.2.24)"
NOTE_NEW_ERROR = "1.4.3: error {code:04d} is in 8.2 of 1.4.3, not in NIST's table"

COORD_SYSTEMS = ("MachineCsy", "MoveableMachineCsy", "MultipleArmCsy", "PartCsy")
MACHINE_CLASSES = ("CartCMM", "CartCMMWithRotaryTable")
PARAMETER_PARTS = ("Act", "Def", "Max", "Min")
GOTO_PARS = ("Speed", "Accel")
PTMEAS_PARS = ("Speed", "Accel", "Approach", "Retract", "Search")
SINGLE_ITEMS = ("ER", "R", "X", "Y", "Z")


def _fail(name: str, message: str) -> Fail:
    return Fail(f"{name}: {message}" if name else message)


def error_response(t: Tokens, text: str, notes: list[str]) -> None:
    """``Error(F1, F2, F3, Text)``: a one-digit severity, a four-digit number, F3 and Text strings (6.1.4.2); the
    number must be in the table of 8.2 and the text and default severity its own."""
    name = "ErrorResponse"
    if t.shape != "k(n,n,s,s)":
        raise _fail(name, "BAD RESPONSE ITEMS")
    if t.word(0) != "Error":
        raise _fail(name, "RESPONSE NAME MUST BE ERROR")
    if text[15:16] != ",":
        raise _fail(name, "SEVERITY MUST HAVE ONE DIGIT")
    if not (text[16:20].isdigit() and text[16:20].isascii() and text[20:21] == ","):
        raise _fail(name, "ERROR CODE MUST HAVE FOUR DIGITS")
    severity = {0.0: "0", 1.0: "1", 2.0: "2", 3.0: "3", 9.0: "9"}.get(t.number(2), "4")
    code = int(t.number(4))
    known = NIST_ERRORS.get(code)
    if known is None and code in ERRORS_1_4_3:
        known = ERRORS_1_4_3[code]
        notes.append(NOTE_NEW_ERROR.format(code=code))
    if known is None:
        raise _fail(name, "BAD ERROR CODE")
    message = str(t.value(8))
    if code == 6 and message == TEXT_0006_1_4_3:
        notes.append(NOTE_0006)
    elif message != known[1]:
        raise _fail(name, "BAD TEXT")
    if severity != known[0]:
        raise _fail(name, "BAD SEVERITY")


def _boolean(t: Tokens, text: str, name: str, close_at: int) -> None:
    if t.shape != "k(n)" or text[close_at : close_at + 1] != ")":
        raise _fail(name, "BAD RESPONSE ITEMS")
    if t.number(2) not in (0.0, 1.0):
        raise _fail(name, "VALUE MUST BE 0 OR 1")


def _exact(t: Tokens, name: str, shape: str) -> None:
    if t.shape != shape:
        raise _fail(name, "BAD RESPONSE ITEMS")


def data_response(t: Tokens, text: str, notes: list[str]) -> None:
    """A ``#`` line of a transaction: which response it is follows from its first items, as in NIST's parser."""
    first = t.word(0)
    if t.kind(0) == "(":
        if t.shape not in ("(n,n,n)", "(n,n,n,n,n,n)"):
            raise _fail("AlignResponse", "BAD RESPONSE ITEMS")
    elif first == "CenterPart":
        _boolean(t, text, "CenterPartResponse", 20)
    elif t.kind(0) == "s" and len(t) == 3:
        _exact(t, "EnumPropResponse", "s,s")
    elif first == "ChangeToolAction":
        name = "ChangeToolActionResponse"
        if t.shape != "k(k,k(n),k(n),k(n))" or (t.word(4), t.word(9), t.word(14)) != ("X", "Y", "Z"):
            raise _fail(name, "BAD RESPONSE ITEMS")
        if t.word(2) not in ("Switch", "Rotate", "MoveAuto", "MoveMan"):
            raise _fail(name, "FIRST ARGUMENT MUST BE SWITCH ROTATE MOVEAUTO OR MOVEMAN")
    elif first == "CoordSystem":
        _exact(t, "GetCoordSystemResponse", "k(k)")
        if t.word(2) not in COORD_SYSTEMS:
            raise _fail("GetCoordSystemResponse", "BAD COORDINATE SYSTEM")
    elif first == "GetCsyTransformation":
        _exact(t, "GetCsyTransformationResponse", "k(n,n,n,n,n,n)")
    elif first == "DMEVersion":
        _exact(t, "GetDMEVersionResponse", "k(s)")
    elif first == "ErrStatus":
        _boolean(t, text, "GetErrStatusEResponse", 19)
    elif first == "GetMachineClass":
        _machine_class(t, notes)
    elif first == "FoundTool" or (first == "Tool" and t.word(2) not in ("A", "B", "C")):
        get_prop_response(t, notes)
    elif first == "IsHomed":
        _boolean(t, text, "IsHomedResponse", 17)
    elif first == "IsUserEnabled":
        _boolean(t, text, "IsUserEnabledResponse", 23)
    elif first in (*SINGLE_ITEMS, "IJK", "Tool", "Q"):
        if first == "Q":
            notes.append(NOTE_Q)
        measured_items(t, 0, "PtMeasOrGetResponse", notes)
    elif t.kind(0) == "n":
        if len(t) % 2 != 1 or any(t.kind(i) != ("n" if i % 2 == 0 else ",") for i in range(len(t))):
            raise _fail("ScanResponse", "BAD RESPONSE ITEMS")
    elif t.kind(0) == "s" and len(t) == 1:
        return
    elif first == "TiltCenterPart":
        _boolean(t, text, "TiltCenterPartResponse", 24)
    elif first == "TiltPart":
        _boolean(t, text, "TiltPartResponse", 18)
    else:
        raise Fail("BAD RESPONSE ITEMS")


def _machine_class(t: Tokens, notes: list[str]) -> None:
    name = "GetMachineClassResponse"
    if t.shape == "k(k)" and t.word(2) in MACHINE_CLASSES:
        notes.append(NOTE_MACHINE_CLASS)
        return
    _exact(t, name, "k(s)")
    if t.value(2) not in MACHINE_CLASSES:
        raise _fail(name, "BAD MACHINE CLASS")


def get_prop_response(t: Tokens, notes: list[str]) -> None:
    """``[Found]Tool.<property>(value), ...`` (GetProp, GetPropE)."""
    name = "GetPropResponse"
    n = 0
    while n < len(t):
        if (len(t) < n + 5 or t.word(n) not in ("Tool", "FoundTool") or t.kind(n + 1) != "."
                or t.kind(n + 2) != "k"):
            raise _fail(name, "BAD RESPONSE ITEMS")
        found, key2 = t.word(n) == "FoundTool", t.word(n + 2)
        if key2 in ("GoToPar", "PtMeasPar"):
            n = _number_property(t, n, name)
        elif key2 in ("Alignment", "CollisionVolume") and found:
            raise _fail(name, "BAD SECOND KEYWORD")
        elif key2 == "Alignment":
            n = _alignment(t, n, name)
        elif key2 == "CollisionVolume":
            n = _collision_volume(t, n, name)
        elif key2 in ("Name", "Id"):
            n = _one_item(t, n, name, "s")
        elif key2 == "AvrRadius" and not found:
            notes.append(NOTE_AVR_RADIUS)
            n = _one_item(t, n, name, "n")
        else:
            raise _fail(name, "BAD SECOND KEYWORD")


def _followed(t: Tokens, at: int) -> bool:
    """The item at ``at`` ends the line or is a comma."""
    return len(t) == at or t.kind(at) == ","


def _one_item(t: Tokens, m: int, name: str, kind: str) -> int:
    if len(t) < m + 6 or t.shape[m + 3 : m + 6] != f"({kind})" or not _followed(t, m + 6):
        raise _fail(name, "BAD RESPONSE ITEMS")
    return m + 7


def _number_property(t: Tokens, m: int, name: str) -> int:
    if t.kind(m + 3) != ".":
        raise _fail(name, "BAD RESPONSE ITEMS")
    if _followed(t, m + 10) and len(t) >= m + 10:
        if (t.kind(m + 5) != "." or t.word(m + 6) not in PARAMETER_PARTS
                or t.shape[m + 7 : m + 10] != "(n)"):
            raise _fail(name, "BAD RESPONSE ITEMS")
        after = m + 11
    elif _followed(t, m + 8) and len(t) >= m + 8:
        if t.shape[m + 5 : m + 8] != "(n)":
            raise _fail(name, "BAD RESPONSE ITEMS")
        after = m + 9
    else:
        raise _fail(name, "BAD RESPONSE ITEMS")
    if t.word(m + 2) == "GoToPar" and t.word(m + 4) not in GOTO_PARS:
        raise _fail(name, "BAD GOTOPAR PROPERTY")
    if t.word(m + 2) == "PtMeasPar" and t.word(m + 4) not in PTMEAS_PARS:
        raise _fail(name, "BAD PTMEASPAR PROPERTY")
    return after


def _alignment(t: Tokens, m: int, name: str) -> int:
    if len(t) < m + 10 or t.shape[m + 3 : m + 9] != "(n,n,n":
        raise _fail(name, "BAD RESPONSE ITEMS")
    if _followed(t, m + 10):
        if t.kind(m + 9) != ")":
            raise _fail(name, "BAD RESPONSE ITEMS")
        return m + 11
    if len(t) >= m + 16 and _followed(t, m + 16):
        if t.shape[m + 9 : m + 16] != ",n,n,n)":
            raise _fail(name, "BAD RESPONSE ITEMS")
        return m + 17
    raise _fail(name, "BAD RESPONSE ITEMS")


def _collision_volume(t: Tokens, m: int, name: str) -> int:
    k = m + 3
    if t.kind(k) != "(":
        raise _fail(name, "BAD RESPONSE ITEMS")
    if t.kind(k + 1) == ")":
        if len(t) != k + 2 and t.kind(k + 2) != ",":
            raise _fail(name, "BAD RESPONSE ITEMS")
        return m + 6
    boxes = 0
    while True:
        boxes += 1
        if len(t) < k + 32 or t.word(k + 1) != "OBB" or t.shape[k + 2 : k + 32] != ",n" * 15:
            raise _fail(name, "BAD RESPONSE ITEMS")
        k += 2
        if t.kind(k + 30) == ")":
            break
        if t.kind(k + 30) != ",":
            raise _fail(name, "BAD RESPONSE ITEMS")
        k += 30
    if len(t) != k + 31 and t.kind(k + 31) != ",":
        raise _fail(name, "BAD RESPONSE ITEMS")
    return m + 5 + boxes * 32


def measured_items(t: Tokens, start: int, name: str, notes: list[str], enclosed: bool = False,
                   zero_ijk: bool = False) -> None:
    """``X(x), Y(y), Z(z), IJK(i,j,k), ER(r), R(r), Tool.A(a), ...`` each at most once: a PtMeas or Get report, or
    (``enclosed``) the inside of a server's ``GoTo(..)`` or ``PtMeas(..)`` event, whose IJK must be zero for GoTo."""
    seen: set[str] = set()
    n = start
    while n < len(t):
        def end_ok(at: int) -> bool:
            if enclosed:  # the last item closes the event's parenthesis
                return (t.kind(at) == ")" and len(t) == at + 1) or (t.kind(at) == "," and len(t) > at + 1)
            return _followed(t, at)

        need = 5 if enclosed else 4
        if len(t) < n + need or t.kind(n) != "k":
            raise _fail(name, "BAD RESPONSE ITEMS")
        word = t.word(n)
        if word in (*SINGLE_ITEMS, "Q"):
            if t.shape[n + 1 : n + 4] != "(n)" or not end_ok(n + 4):
                raise _fail(name, "BAD RESPONSE ITEMS")
            item, n = word, n + 5
            if word == "Q" and NOTE_Q not in notes:
                notes.append(NOTE_Q)
        elif word == "Tool":
            if len(t) < n + (7 if enclosed else 6) or t.shape[n + 1 : n + 6] != ".k(n)" or not end_ok(n + 6):
                raise _fail(name, "BAD RESPONSE ITEMS")
            if t.word(n + 2) not in ("A", "B", "C"):
                raise _fail(name, "BAD RESPONSE ITEMS")
            item, n = f"TOOL {t.word(n + 2)}", n + 7
        elif word == "IJK":
            if len(t) < n + (9 if enclosed else 8) or t.shape[n + 1 : n + 8] != "(n,n,n)" or not end_ok(n + 8):
                raise _fail(name, "BAD RESPONSE ITEMS")
            if "IJK" in seen:
                raise _fail(name, "IJK USED TWICE")
            if zero_ijk and any(t.number(n + k) != 0.0 for k in (2, 4, 6)):
                raise _fail(name, "IJK VALUES MUST BE ZERO")
            item, n = "IJK", n + 9
        else:
            raise _fail(name, "BAD RESPONSE ITEMS")
        if item in seen:
            raise _fail(name, f"{item} USED TWICE")
        seen.add(item)


def server_initiated(t: Tokens, notes: list[str]) -> None:
    """An ``E0000 #`` line (9.5): ChangeTool, GoTo, KeyPress, PtMeas or SetProp."""
    first = t.word(0)
    if first == "ChangeTool":
        _exact(t, "ChangeToolEResponse", "k(s)")
    elif first == "KeyPress":
        _exact(t, "KeyPressEResponse", "k(s)")
    elif first in ("GoTo", "PtMeas"):
        name = "GoToEResponse" if first == "GoTo" else "PtMeasEResponse"
        if t.kind(1) != "(":
            raise _fail(name, "BAD RESPONSE ITEMS")
        measured_items(t, 2, name, notes, enclosed=True, zero_ijk=first == "GoTo")
    elif first == "SetProp":
        _set_prop_event(t)
    else:
        raise Fail("BAD RESPONSE ITEMS")


def _set_prop_event(t: Tokens) -> None:
    name = "SetPropEResponse"
    if len(t) < 11 or t.shape[1:7] != "(k.k.k":
        raise _fail(name, "BAD RESPONSE ITEMS")
    key2, key3 = t.word(4), t.word(6)
    if (t.word(2) not in ("Tool", "FoundTool") or key2 not in ("GoToPar", "PtMeasPar")
            or key3 not in (GOTO_PARS if key2 == "GoToPar" else PTMEAS_PARS)):
        raise _fail(name, "BAD KEYWORD")
    if len(t) == 11:
        _exact(t, name, "k(k.k.k(n))")
    elif len(t) == 13:
        _exact(t, name, "k(k.k.k.k(n))")
        if t.word(8) != "Act":
            raise _fail(name, "BAD KEYWORD")
    else:
        raise _fail(name, "BAD RESPONSE ITEMS")
