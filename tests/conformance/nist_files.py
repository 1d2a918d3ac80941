"""Loader of NIST's I++ DME test suite files: ``.prg``/``.res`` entries, the ``.txt`` outcomes, the ClientServerLogs.

Test support, not product code. The files (README of the suite): entries separated by lines holding ``\\\\``, the
file ended by ``:`` lines; an entry may span lines (NIST's parsers then see the inner CR LF). ``.txt`` files give, for
the bad examples, NIST's own message (and for commands the I++ error number) after the entry's text. The logs hold one
``<date>_<time> Sent|Received|received: <line>`` record per line sent or received, blank lines between.

The directory is ``$HILCAL_NIST_DIR`` or the shared reference copy; ``nist_dir()`` is None when neither exists.
"""

from __future__ import annotations

import os
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

DEFAULT_NIST_DIR = Path("/work/shared/reference/ippdme/nist_test_files")
SEPARATOR = b"\\\\"
END = b":"


def nist_dir() -> Path | None:
    """The NIST test file directory, or None when it is not available here."""
    path = Path(os.environ.get("HILCAL_NIST_DIR", DEFAULT_NIST_DIR))
    return path if path.is_dir() else None


@dataclass(frozen=True)
class Entry:
    """One entry of a ``.prg`` or ``.res`` file."""

    file: str
    index: int
    """0-based position in its file."""
    line_no: int
    """1-based line of the entry's first line."""
    text: str
    """The entry without its final line terminator; an entry spanning lines keeps its inner terminators."""

    @property
    def lines(self) -> list[str]:
        return re.split(r"\r?\n", self.text)

    @property
    def tag(self) -> str:
        return self.text[:5]


def read_entries(path: Path) -> list[Entry]:
    """The entries of a ``.prg`` or ``.res`` file, in order (bytes decoded as Latin-1: any byte is kept)."""
    raw = path.read_bytes()
    entries: list[Entry] = []
    current: list[bytes] = []
    start = 1
    for number, line in enumerate(raw.split(b"\n"), start=1):
        body = line.removesuffix(b"\r")
        if body == SEPARATOR or body == END:
            if current:
                text = b"\n".join(current).decode("latin-1")
                entries.append(Entry(path.name, len(entries), start, text.removesuffix("\r")))
            current = []
            start = number + 1
            if body == END:
                break
            continue
        if not current:
            start = number
        current.append(line)
    return entries


@dataclass(frozen=True)
class Outcome:
    """What NIST's ``.txt`` says about one entry: accepted, or its message (and I++ error number for commands)."""

    entry: Entry
    accepted: bool
    message: str = ""
    ipp_error: int | None = None


def read_outcomes(txt: Path, entries: list[Entry]) -> list[Outcome]:
    """Align a ``.txt`` file with the entries it describes (in order; entries it omits, such as the ClearAllErrors
    between the bad commands, get no outcome). After an entry's lines: ``\\\\`` (accepted) or the message line and,
    for commands, the four-digit I++ error number."""
    lines = [line.rstrip("\r") for line in txt.read_text(encoding="latin-1").split("\n")]
    out: list[Outcome] = []
    pos = 0
    for entry in entries:
        body = entry.lines
        at = _find(lines, body, pos)
        if at is None:
            continue
        after = at + len(body)
        rest: list[str] = []
        while after < len(lines) and lines[after].strip() and len(rest) < 2:
            rest.append(lines[after])
            after += 1
        if not rest:
            continue
        if rest[0] == "\\\\":
            out.append(Outcome(entry, True))
            pos = at + len(body) + 1
            continue
        number = int(rest[1]) if len(rest) > 1 and re.fullmatch(r"[0-9]{4}", rest[1]) else None
        out.append(Outcome(entry, False, rest[0], number))
        pos = at + len(body) + (2 if number is not None else 1)
    return out


def _find(lines: list[str], body: list[str], start: int) -> int | None:
    for i in range(start, len(lines) - len(body) + 1):
        if lines[i : i + len(body)] == body:
            return i
    return None


@dataclass(frozen=True)
class LogRecord:
    """One record of a ClientServerLogs file."""

    time: str
    direction: Literal["sent", "received", "note"]
    """From the log owner's point of view; ``note`` for the server's own remarks (``Parser: ...``)."""
    text: str


_LOG = re.compile(r"^(\S+) (Sent|Received|received|[A-Za-z]+): ?(.*)$")


def read_log(path: Path) -> list[LogRecord]:
    """The records of ``X_Client.log`` or ``X_Server.log`` in order."""
    out: list[LogRecord] = []
    for line in path.read_text(encoding="latin-1").splitlines():
        line = line.rstrip("\r")
        m = _LOG.match(line)
        if m is None:
            continue
        word = m.group(2).lower()
        direction: Literal["sent", "received", "note"] = (
            "sent" if word == "sent" else "received" if word == "received" else "note")
        out.append(LogRecord(m.group(1), direction, m.group(3).rstrip("\r")))
    return out


def log_paths(name: str) -> tuple[Path, Path] | None:
    """(client log, server log) of a program, or None when the suite has none."""
    base = nist_dir()
    if base is None:
        return None
    logs = base / "ClientServerLogs"
    for sep in ("_", "."):
        client, server = logs / f"{name}{sep}Client.log", logs / f"{name}{sep}Server.log"
        if client.is_file() and server.is_file():
            return client, server
    return None


def programs() -> list[Path]:
    """Every ``.prg`` file of the suite, sorted."""
    base = nist_dir()
    return [] if base is None else sorted(base.glob("*.prg"))


def responses_by_tag(entries: list[Entry]) -> dict[str, list[str]]:
    """A ``.res`` file's response lines grouped by tag, in order (a reference server's answers to the ``.prg``)."""
    out: dict[str, list[str]] = {}
    for entry in entries:
        for line in entry.lines:
            out.setdefault(line[:5], []).append(line)
    return out
