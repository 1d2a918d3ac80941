"""The data the CMM driver reads out of I++ DME answers, each checked against what was asked (6.2.2.2: "the returned
data must exactly match the requested data. No data may be omitted and no data may be added").

Every reader raises ``CmmProtocolError`` when the answer does not hold what it needs, and reports what it tolerates
(items in another order than asked, a 1.4-era String for the machine class) through the ``note`` callback the link
logs as ``cmm.nonconformant``.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from drivers.cmm.forms import Kind, Note
from drivers.cmm.link import Transaction
from drivers.cmm.types import CmmProtocolError
from drivers.cmm.wire import Arg, Item, ResponseLine, Word, parse_response
from hilcal.protocols.ippdme import MACHINE_CLASSES

NoteSink = Callable[[Note, str], None]


def _quiet(note: Note, raw: str) -> None:
    return None


def requested_items(command_line: str) -> list[str]:
    """The names of the items a ``Get(...)``, ``GetProp(...)`` or ``OnPtMeasReport(...)`` command line asks for."""
    line = parse_response(f"{command_line[:5]} # {command_line[6:]}")
    if len(line.values) != 1 or not isinstance(line.values[0], Item):
        raise ValueError(f"not a method call: {command_line!r}")
    return [a.name for a in line.values[0].args if isinstance(a, Item)]


def one_line(tx: Transaction) -> ResponseLine:
    """The single data line of a transaction."""
    if len(tx.data) != 1:
        raise CmmProtocolError(f"{tx.line}: {len(tx.data)} data lines, expected 1")
    return tx.data[0]


def report(line: ResponseLine, asked: list[str], note: NoteSink = _quiet) -> dict[str, tuple[Arg, ...]]:
    """An answer's items by name (Get, PtMeas, GetProp): exactly the items asked; items in another order than asked
    are tolerated and noted."""
    items = [v for v in line.values if isinstance(v, Item)]
    names = [it.name for it in items]
    if len(items) != len(line.values) or sorted(names) != sorted(asked):
        raise CmmProtocolError(f"{line.raw!r} does not hold exactly the items asked ({', '.join(asked)})")
    if names != asked:
        note(Note(Kind.NONCONFORMANT, f"items reported in another order than asked ({', '.join(asked)}): "
                  "OnPtMeasReport and Get define the sequence (6.3.2.6)"), line.raw)
    return {it.name: it.args for it in items}


def positions(line: ResponseLine, asked: list[str], note: NoteSink = _quiet) -> dict[str, tuple[float, ...]]:
    """A report of numbers (Get, PtMeas): ``report`` with every item holding numbers only."""
    out = {}
    for name, args in report(line, asked, note).items():
        if not args or not all(isinstance(a, float) for a in args):
            raise CmmProtocolError(f"{line.raw!r}: {name} does not hold numbers")
        out[name] = tuple(float(a) for a in args)  # type: ignore[arg-type]
    return out


def xyz(values: dict[str, tuple[float, ...]]) -> np.ndarray:
    """X, Y, Z of a report as a (3,) array (mm)."""
    try:
        return np.array([values["X"][0], values["Y"][0], values["Z"][0]])
    except (KeyError, IndexError):
        raise CmmProtocolError(f"the report lacks X, Y or Z: {values}") from None


def flag(tx: Transaction, name: str) -> bool:
    """``Name(0|1)`` (IsHomed, ErrStatus, IsUserEnabled)."""
    line = one_line(tx)
    it = line.items().get(name)
    if it is None or len(line.values) != 1 or len(it.args) != 1 or it.args[0] not in (0.0, 1.0):
        raise CmmProtocolError(f"{tx.line}: expected {name}(0) or {name}(1), got {line.raw!r}")
    return it.args[0] == 1.0


def strings(tx: Transaction) -> list[str]:
    """The first String of every data line (EnumTools: one name a line, 6.3.2.23; GetErrorInfo: one, 6.3.1.6)."""
    out = []
    for line in tx.data:
        if not line.values or not isinstance(line.values[0], str):
            raise CmmProtocolError(f"{tx.line}: expected a String, got {line.raw!r}")
        out.append(line.values[0])
    return out


def string_item(tx: Transaction, name: str) -> str:
    """``Name("text")``: DMEVersion (6.3.1.14), Tool.Name (6.3.10)."""
    it = one_line(tx).items().get(name)
    if it is None or len(it.args) != 1 or not isinstance(it.args[0], str):
        raise CmmProtocolError(f"{tx.line}: expected {name}(\"...\"), got {[d.raw for d in tx.data]}")
    return it.args[0]


def machine_class(tx: Transaction, note: NoteSink = _quiet) -> str:
    """GetMachineClass's answer (6.3.2.8: an enumeration since 1.4.3; a 1.4-era String accepted and noted)."""
    line = one_line(tx)
    it = line.items().get("GetMachineClass")
    value = it.args[0] if it is not None and len(it.args) == 1 else None
    if isinstance(value, Word) and value.name in MACHINE_CLASSES:
        return value.name
    if isinstance(value, str) and value in MACHINE_CLASSES:
        note(Note(Kind.VERSION, "GetMachineClass answered with a String, as before 1.4.3"), line.raw)
        return value
    raise CmmProtocolError(f"{tx.line}: expected GetMachineClass({' | '.join(MACHINE_CLASSES)}), got {line.raw!r}")


def numbers(tx: Transaction, asked: list[str], note: NoteSink = _quiet) -> dict[str, float]:
    """A GetProp answer of one number per property (PtMeasPar, AvrRadius), by the names asked."""
    values = positions(one_line(tx), asked, note)
    bad = [k for k, v in values.items() if len(v) != 1]
    if bad:
        raise CmmProtocolError(f"{tx.line}: {', '.join(bad)} must hold one number")
    return {k: v[0] for k, v in values.items()}
