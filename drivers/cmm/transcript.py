"""The CMM conversation as it went over the wire: every line sent and received, in order, one per line as
``<ISO time> > <line>`` (sent) and ``<ISO time> < <line>`` (received), without the CR LF.

A CMM vendor's support asks for this first. The run folder keeps it as ``instrument_transcript.txt``
(``procedures.station.open_devices``). A received byte outside ASCII 32..126 (which the protocol forbids, 6.1.1) is
written as ``\\xNN`` so the file stays one line per line; everything else is exactly as on the wire.
"""

from __future__ import annotations

import re
import threading
from datetime import UTC, datetime
from pathlib import Path
from typing import Protocol, TextIO

TRANSCRIPT_NAME = "instrument_transcript.txt"
SENT, RECEIVED = ">", "<"


class TranscriptSink(Protocol):
    """Where the driver writes its conversation."""

    def write(self, direction: str, line: str) -> None:
        """One line: ``direction`` is ``SENT`` or ``RECEIVED``."""


_UNPRINTABLE = re.compile(rb"[^\x20-\x7e]")


def printable(raw: bytes) -> str:
    """A received line as text: ASCII 32..126 as they are, any other byte as ``\\xNN``."""
    return _UNPRINTABLE.sub(lambda m: b"\\x%02x" % m.group()[0], raw).decode("ascii")


def stamp() -> str:
    """Now, UTC, ISO 8601 to the microsecond."""
    return datetime.now(UTC).isoformat(timespec="microseconds")


class TranscriptFile:
    """Appends to a file, flushed line by line (a run that stops leaves every line it got)."""

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        self._lock = threading.Lock()
        self._file: TextIO | None = self.path.open("a", encoding="ascii", newline="\n")

    def write(self, direction: str, line: str) -> None:
        with self._lock:
            if self._file is not None:
                self._file.write(f"{stamp()} {direction} {line}\n")
                self._file.flush()

    def close(self) -> None:
        with self._lock:
            if self._file is not None:
                self._file.close()
                self._file = None


class TranscriptMemory:
    """Keeps the lines in memory (tests, the benchmark)."""

    def __init__(self) -> None:
        self.lines: list[str] = []

    def write(self, direction: str, line: str) -> None:
        self.lines.append(f"{stamp()} {direction} {line}")

    def sent(self) -> list[str]:
        """The lines sent, without their time."""
        return [x.split(" ", 2)[2] for x in self.lines if x.split(" ", 2)[1] == SENT]

    def received(self) -> list[str]:
        """The lines received, without their time."""
        return [x.split(" ", 2)[2] for x in self.lines if x.split(" ", 2)[1] == RECEIVED]
