"""What a parsed I++ DME response line means, checked against the specification: the data forms of section 6.3 and
9.5 and the error table of 8.2 (``hilcal.protocols.ippdme``).

``check_response(line)`` returns notes, never raises: the driver logs them (``cmm.nonconformant``) and decides what to
do with the data it needs. A note's kind says how far the line is from 1.4.3:

* ``problem``: the line breaks a data form of the specification (a flag that is not 0 or 1, an item given twice,
  an unknown name, a property that cannot be reported);
* ``nonconformant``: allowed or tolerable, but not as the specification writes it: an error text other than the
  table's (8.1: "must be the text string shown in section 8.2"), an adapted severity (8.1 allows it), F3 as a bare
  name, the parenthesised number list of NIST's reference server;
* ``version``: a form of another version of the specification: 1.4.3 made GetMachineClass's answer an enumeration
  (6.3.2.8), named error 0006 "... To Continue", added Tool.AvrRadius() (6.3.13) and Q() (6.3.2.24); NIST's 1.4-era
  parsers know the older forms;
* ``extension``: what 8.1 and 9.1 leave to a server: error numbers 8000-8999, vendor properties (``XX.Name``).
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from enum import StrEnum

from drivers.cmm.wire import Arg, ErrorReport, Form, Item, ResponseLine, Word
from hilcal.protocols.ippdme import (
    CHANGE_TOOL_ACTIONS,
    COORD_SYSTEMS,
    ERRORS,
    GO_TO_PARAMETERS,
    MACHINE_CLASSES,
    PARAMETER_PARTS,
    PT_MEAS_PARAMETERS,
    SERVER_DEFINED_CODES,
    Code,
    Marker,
)

POSITION_ITEMS = frozenset({"X", "Y", "Z", "R", "ER", "Q", "Tool.A", "Tool.B", "Tool.C"})
"""Report items holding one number (6.3.2.6, 6.3.2.11, 6.3.3); IJK holds three."""
FLAG_ITEMS = frozenset({"IsHomed", "IsUserEnabled", "ErrStatus", "CenterPart", "TiltPart", "TiltCenterPart"})
"""Data ``Name(Bool)``: 0 or 1 (6.3.2.2, 6.3.2.5, 6.3.2.9, 13.1-13.3)."""
SCAN_PARAMETERS = ("Speed", "Accel", "Retract")
"""6.3.15: the ScanPar block (since 1.4.3 in the tool's property tree)."""
ENUM_PROP_TYPES = ("Number", "String", "Property")
"""6.3.1.12: the types EnumProp names."""
SERVER_EVENT_METHODS = ("KeyPress", "GoTo", "PtMeas", "ChangeTool", "SetProp")
"""9.5: the predefined server events (data under E0000)."""
VERSION_0006_TEXT = "Transaction aborted (Use ClearAllErrors to Continue)"
"""Error 0006's text before 1.4.3 (NIST's 1.4-era table); 1.4.3 writes "To"."""
_VENDOR = re.compile(r"[A-Z]{2}\.")


class Kind(StrEnum):
    PROBLEM = "problem"
    NONCONFORMANT = "nonconformant"
    VERSION = "version"
    EXTENSION = "extension"


@dataclass(frozen=True)
class Note:
    """What ``check_response`` found: its kind (module docstring) and a sentence."""

    kind: Kind
    text: str


def check_response(line: ResponseLine) -> list[Note]:
    """The notes on one parsed response line (empty: it is as 1.4.3 writes it)."""
    if line.marker is Marker.ERROR and line.error is not None:
        return check_error(line.error)
    if line.marker is not Marker.DATA:
        return []
    if line.form is Form.NUMBERS:
        return []
    if line.form is Form.STRINGS:
        if len(line.values) == 2 and line.values[1] not in ENUM_PROP_TYPES:
            return [_problem(f"an EnumProp type is one of {', '.join(ENUM_PROP_TYPES)}, not {line.values[1]!r}")]
        return []
    if line.form is Form.VECTOR:
        if len(line.values) not in (3, 6):
            return [_problem(f"an AlignTool/AlignPart vector list holds 3 or 6 numbers, not {len(line.values)}")]
        return [Note(Kind.NONCONFORMANT, "a parenthesised number list is no data form of 6.1.4.2 (NIST's reference "
                     "server answers AlignTool and AlignPart so)")]
    return _check_items(line)


def check_error(err: ErrorReport) -> list[Note]:
    """An error against the table of 8.2 (and the ranges of 8.1)."""
    notes = []
    if not err.method_quoted:
        notes.append(Note(Kind.NONCONFORMANT, f"F3 {err.method} is a bare name; 6.1.4.2 makes F3 a String (the "
                          "examples of 6.2.3.1 and 8.1 do not quote it)"))
    if err.severity not in (0, 1, 2, 3, 9):
        notes.append(_problem(f"severity {err.severity} is none of 0, 1, 2, 3, 9 (8.1)"))
    spec = ERRORS.get(err.code)
    if spec is None:
        if err.code in SERVER_DEFINED_CODES:
            notes.append(Note(Kind.EXTENSION, f"error {err.code:04d} is defined by the server (8.1: 8000-8999)"))
        else:
            notes.append(_problem(f"error {err.code:04d} is not in the table of 8.2 nor a server-defined number"))
        return notes
    if err.text != spec.text:
        if err.code == Code.TRANSACTION_ABORTED and err.text == VERSION_0006_TEXT:
            notes.append(Note(Kind.VERSION, f"error 0006's text before 1.4.3 ({err.text!r}; 1.4.3: {spec.text!r})"))
        else:
            notes.append(Note(Kind.NONCONFORMANT, f"error {err.code:04d}'s text is {err.text!r}, the table's (8.2) "
                              f"{spec.text!r}"))
    if err.severity != spec.severity and err.severity in (0, 1, 2, 3, 9):
        notes.append(Note(Kind.NONCONFORMANT, f"error {err.code:04d} with severity {err.severity}, the table's "
                          f"default {int(spec.severity)} (8.1 lets a server adapt it)"))
    return notes


def _problem(text: str) -> Note:
    return Note(Kind.PROBLEM, text)


def _numbers(item: Item, n: int | tuple[int, ...]) -> bool:
    counts = (n,) if isinstance(n, int) else n
    return len(item.args) in counts and all(isinstance(a, float) for a in item.args)


def _check_items(line: ResponseLine) -> list[Note]:
    items = [v for v in line.values if isinstance(v, Item)]
    first = items[0].name
    if _VENDOR.match(first):
        return [Note(Kind.EXTENSION, f"{first} is a vendor extension (9.1)")]
    if line.is_server_event:
        return _server_event(items)
    if first in ("GoTo", "PtMeas", "KeyPress", "ChangeTool", "SetProp"):
        return [_problem(f"{first}(...) is a server event: it comes with tag E0000 (9.5)")]
    if first in POSITION_ITEMS or first == "IJK":
        return _positions(items, "a position report")
    if first.startswith(("Tool.", "FoundTool.")):
        notes: list[Note] = []
        for it in items:
            notes += _property(it)
        return notes
    if len(items) != 1:
        return [_problem(f"{first}(...) stands alone in its response, here with {len(items) - 1} more item(s)")]
    return _single(items[0])


def _single(it: Item) -> list[Note]:
    a = it.args
    if it.name in FLAG_ITEMS:
        return [] if _numbers(it, 1) and a[0] in (0.0, 1.0) else [_problem(f"{it} must be {it.name}(0) or (1)")]
    if it.name == "DMEVersion":
        return [] if len(a) == 1 and isinstance(a[0], str) else [_problem(f"{it}: DMEVersion(\"version\"), 6.3.1.14")]
    if it.name == "GetMachineClass":
        if len(a) == 1 and isinstance(a[0], Word) and a[0].name in MACHINE_CLASSES:
            return []
        if len(a) == 1 and isinstance(a[0], str) and a[0] in MACHINE_CLASSES:
            return [Note(Kind.VERSION, f"{it}: a String before 1.4.3; since 1.4.3 an enumeration (6.3.2.8)")]
        return [_problem(f"{it}: the machine class is one of {', '.join(MACHINE_CLASSES)} (6.3.2.8)")]
    if it.name == "CoordSystem":
        ok = len(a) == 1 and isinstance(a[0], Word) and a[0].name in COORD_SYSTEMS
        return [] if ok else [_problem(f"{it}: CoordSystem({' | '.join(COORD_SYSTEMS)}) (6.3.3.2)")]
    if it.name == "GetCsyTransformation":
        return [] if _numbers(it, 6) else [_problem(f"{it}: six numbers X0, Y0, Z0, Theta, Psi, Phi (6.3.3.3)")]
    if it.name == "ChangeToolAction":
        ok = (len(a) == 4 and isinstance(a[0], Word) and a[0].name in CHANGE_TOOL_ACTIONS
              and all(isinstance(x, Item) and x.name == n and _numbers(x, 1)
                      for x, n in zip(a[1:], "XYZ", strict=True)))
        return [] if ok else [_problem(f"{it}: ChangeToolAction({' | '.join(CHANGE_TOOL_ACTIONS)}, X(), Y(), Z()) "
                                       "(6.3.2.26)")]
    return [_problem(f"{it.name}(...) is no data of the specification")]


def _positions(items: list[Item], what: str, event: str = "") -> list[Note]:
    """Position report items (Get, PtMeas, OnPtMeasReport, 9.5 GoTo/PtMeas events): each known, each once."""
    notes, seen = [], set()
    for it in items:
        if it.name in seen:
            notes.append(_problem(f"{it.name} given twice in {what}"))
        seen.add(it.name)
        if it.name == "IJK":
            if not _numbers(it, 3):
                notes.append(_problem(f"{it}: IJK(i, j, k)"))
            elif event == "GoTo" and any(x != 0.0 for x in it.args):
                notes.append(_problem(f"{it}: a GoTo event's vectors are IJK(0, 0, 0) (9.5.2)"))
        elif it.name in POSITION_ITEMS:
            if not _numbers(it, 1):
                notes.append(_problem(f"{it}: {it.name}(number)"))
            elif it.name == "Q":
                notes.append(Note(Kind.VERSION, "Q() in a report is 1.4.3's (6.3.2.24); NIST's 1.4 parser refuses it"))
        else:
            notes.append(_problem(f"{it.name} is no report item of {what} (6.3.2.6, 6.3.2.11)"))
    return notes


def _parameter(path: list[str], block: tuple[str, ...]) -> bool:
    """``Speed`` or ``Speed.Max`` etc. of a parameter block (6.3.6, 6.3.7, 6.3.15)."""
    return (len(path) == 1 and path[0] in block) or (len(path) == 2 and path[0] in block
                                                     and path[1] in PARAMETER_PARTS)


def _property(it: Item, settable_only: bool = False) -> list[Note]:
    """One ``Tool.…``/``FoundTool.…`` property in a GetProp answer (6.3.1.9, 6.3.5-6.3.15) or a SetProp event."""
    owner, _, rest = it.name.partition(".")
    path = rest.split(".") if rest else []
    if owner not in ("Tool", "FoundTool") or not path:
        return [_problem(f"{it.name}: a property of Tool or FoundTool")]
    head, a = path[0], it.args
    if head in ("GoToPar", "PtMeasPar", "ScanPar"):
        block = {"GoToPar": GO_TO_PARAMETERS, "PtMeasPar": PT_MEAS_PARAMETERS, "ScanPar": SCAN_PARAMETERS}[head]
        if not _parameter(path[1:], block):
            return [_problem(f"{it.name}: {head} holds {', '.join(block)}, each with {', '.join(PARAMETER_PARTS)}")]
        if settable_only and len(path) == 3 and path[2] != "Act":
            return [_problem(f"{it.name}: only Act can be set (6.3.6, 6.3.7)")]
        notes = [] if _numbers(it, 1) else [_problem(f"{it}: one number")]
        if head == "ScanPar" and not notes:
            notes.append(Note(Kind.VERSION, "ScanPar is in the tool's properties since 1.4.3 (6.3.15)"))
        return notes
    if settable_only:
        return [_problem(f"{it.name}: a server's SetProp event names a GoToPar or PtMeasPar parameter")]
    if len(path) != 1:
        return [_problem(f"{it.name}: no such tool property")]
    if head in ("Name", "Id"):
        return [] if len(a) == 1 and isinstance(a[0], str) else [_problem(f"{it}: {head}(String)")]
    if head == "AvrRadius":
        if not _numbers(it, 1):
            return [_problem(f"{it}: AvrRadius(number)")]
        return [Note(Kind.VERSION, "Tool.AvrRadius() is 1.4.3's (6.3.13); NIST's 1.4 parser does not know it")]
    if head in ("Alignment", "CollisionVolume", "AlignmentVolume") and owner == "FoundTool":
        return [_problem(f"{it.name}: {head} is a property of the active tool only (6.3.11-6.3.14)")]
    if head == "Alignment":
        return [] if _numbers(it, (3, 6)) else [_problem(f"{it}: Alignment(i1, j1, k1[, i2, j2, k2]) (6.3.12)")]
    if head == "CollisionVolume":
        return [] if _boxes(a, "OBB", 15) else [_problem(f"{it}: groups of OBB and 15 numbers (6.3.11)")]
    if head == "AlignmentVolume":
        return [] if _boxes(a, "SPH", 4) else [_problem(f"{it}: AlignmentVolume(SPH, Cx, Cy, Cz, R) (6.3.14)")]
    return [_problem(f"{it.name}: no such tool property")]


def _boxes(args: tuple[Arg, ...], word: str, n: int) -> bool:
    """``word, n numbers`` repeated, at least once."""
    if not args or len(args) % (n + 1):
        return False
    for k in range(0, len(args), n + 1):
        head, nums = args[k], args[k + 1:k + 1 + n]
        if not (isinstance(head, Word) and head.name == word and all(isinstance(x, float) for x in nums)):
            return False
    return True


def _server_event(items: list[Item]) -> list[Note]:
    """Data under E0000: the predefined server events of 9.5."""
    if len(items) != 1 or items[0].name not in SERVER_EVENT_METHODS:
        return [_problem(f"{items[0].name}(...) under E0000 is none of the server events of 9.5 "
                         f"({', '.join(SERVER_EVENT_METHODS)})")]
    it, a = items[0], items[0].args
    if it.name in ("KeyPress", "ChangeTool"):
        return [] if len(a) == 1 and isinstance(a[0], str) else [_problem(f"{it}: {it.name}(String) (9.5)")]
    if it.name == "SetProp":
        if not a or not all(isinstance(x, Item) for x in a):
            return [_problem(f"{it}: SetProp(property(value), ...) (9.5.5)")]
        notes: list[Note] = []
        for x in a:
            notes += _property(x, settable_only=True) if isinstance(x, Item) else []
        return notes
    if not a or not all(isinstance(x, Item) for x in a):
        return [_problem(f"{it}: {it.name}(report items) (9.5.2, 9.5.3)")]
    return _positions([x for x in a if isinstance(x, Item)], f"a {it.name} event", event=it.name)
