"""A minimal I++ DME client for tests (test support code, independent of hilcal's driver): send a command line, read
its transaction until ``%`` with bounded waits, keep the lines of other tags (events) apart.

Works on a TCP connection (``IppClient.tcp(port)``) or a pseudo-terminal (``IppClient.pty(path)``).
"""

from __future__ import annotations

import contextlib
import os
import re
import select
import socket
import termios
import time
import tty
from dataclasses import dataclass, field
from types import TracebackType


@dataclass
class Transaction:
    """What came back for one command: the lines with its tag in order, and the other lines received meanwhile."""

    tag: str
    lines: list[str] = field(default_factory=list)
    others: list[str] = field(default_factory=list)

    @property
    def markers(self) -> str:
        """The seventh characters of the transaction's lines, e.g. ``&#%`` or ``&!%``."""
        return "".join(line[6:7] for line in self.lines)

    @property
    def data(self) -> list[str]:
        return [line[8:] for line in self.lines if line[6:7] == "#"]

    @property
    def errors(self) -> list[int]:
        """The error numbers (F2) of the transaction's ``!`` lines."""
        return [int(line.split(",")[1]) for line in self.lines if line[6:7] == "!"]

    @property
    def event_errors(self) -> list[int]:
        return [int(line.split(",")[1]) for line in self.others if line.startswith("E0000 !")]


class IppClient:
    """One link to an I++ DME server."""

    def __init__(self, fd: int, closer: socket.socket | None = None) -> None:
        self.fd = fd
        self._sock = closer
        self._buffer = b""
        self.pending: list[str] = []
        """Lines read but not yet claimed by a transaction (events, late lines)."""

    @classmethod
    def tcp(cls, port: int, host: str = "127.0.0.1") -> IppClient:
        sock = socket.create_connection((host, port), timeout=5.0)
        sock.setblocking(False)
        return cls(sock.fileno(), sock)

    @classmethod
    def pty(cls, path: str) -> IppClient:
        fd = os.open(path, os.O_RDWR | os.O_NOCTTY | os.O_NONBLOCK)
        tty.setraw(fd)
        termios.tcflush(fd, termios.TCIOFLUSH)
        return cls(fd)

    def send_raw(self, data: bytes) -> None:
        view = memoryview(data)
        deadline = time.monotonic() + 5.0
        while view:
            try:
                view = view[os.write(self.fd, view) :]
            except BlockingIOError:
                if time.monotonic() > deadline:
                    raise TimeoutError("the server does not read") from None
                select.select([], [self.fd], [], 0.05)

    def send(self, line: str) -> None:
        """One command line, CR LF added."""
        self.send_raw(line.encode("latin-1") + b"\r\n")

    def read_line(self, timeout_s: float) -> str:
        """The next response line (terminator removed); TimeoutError if none comes in time."""
        if self.pending:
            return self.pending.pop(0)
        deadline = time.monotonic() + timeout_s
        while b"\r\n" not in self._buffer:
            left = deadline - time.monotonic()
            if left <= 0:
                raise TimeoutError(f"no line within {timeout_s} s (have {self._buffer[:80]!r})")
            ready, _, _ = select.select([self.fd], [], [], left)
            if ready:
                try:
                    chunk = os.read(self.fd, 65536)
                except (BlockingIOError, InterruptedError):
                    continue
                if not chunk:
                    raise ConnectionError("the server closed the link")
                self._buffer += chunk
        line, self._buffer = self._buffer.split(b"\r\n", 1)
        return line.decode("latin-1")

    def read_transaction(self, tag: str, timeout_s: float = 5.0) -> Transaction:
        """Lines until ``tag %`` (for an unreadable tag: until the E0000 error that answers it)."""
        out = Transaction(tag)
        deadline = time.monotonic() + timeout_s
        while True:
            line = self.read_line(max(deadline - time.monotonic(), 0.0))
            if line[:5] == tag and _readable_tag(tag):
                out.lines.append(line)
                if line[6:7] == "%":
                    return out
            else:
                out.others.append(line)
                if line.startswith("E0000 !") and (not _readable_tag(tag) or (not out.lines and ", 0001," in line)):
                    return out  # the answer to a line whose tag is unreadable or not allowed (6.2.1)

    def exchange(self, line: str, timeout_s: float = 5.0) -> Transaction:
        """Send a command line and read its transaction."""
        self.send(line)
        return self.read_transaction(line[:5], timeout_s)

    def drain(self, quiet_s: float = 0.05) -> list[str]:
        """Every line that arrives until the link is quiet for ``quiet_s``."""
        out = list(self.pending)
        self.pending.clear()
        with contextlib.suppress(TimeoutError):
            while True:
                out.append(self.read_line(quiet_s))
        return out

    def close(self) -> None:
        if self._sock is not None:
            self._sock.close()
        else:
            with contextlib.suppress(OSError):
                os.close(self.fd)

    def __enter__(self) -> IppClient:
        return self

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None:
        self.close()


def _readable_tag(tag: str) -> bool:
    return len(tag) == 5 and ((tag.isdigit() and tag != "00000") or (tag[0] == "E" and tag[1:].isdigit()
                                                                      and tag != "E0000"))


class IppError(Exception):
    """A transaction answered with ``!`` lines (the error numbers in ``codes``)."""

    def __init__(self, transaction: Transaction) -> None:
        super().__init__("; ".join(transaction.lines))
        self.transaction = transaction
        self.codes = transaction.errors


class IppSession:
    """Tagged commands over an ``IppClient`` for tests: each call one transaction, ``IppError`` on ``!`` lines."""

    def __init__(self, client: IppClient, timeout_s: float = 5.0) -> None:
        self.client = client
        self.timeout_s = timeout_s
        self._tag = 0
        self.events: list[str] = []

    def next_tag(self) -> str:
        self._tag = self._tag % 99999 + 1
        return f"{self._tag:05d}"

    def call(self, method: str, check: bool = True) -> Transaction:
        """``method`` (e.g. ``"GoTo(X(1))"``) with the next command tag; its transaction."""
        t = self.client.exchange(f"{self.next_tag()} {method}", self.timeout_s)
        self.events += t.others
        if check and "!" in t.markers:
            raise IppError(t)
        return t

    def start(self, home: bool = True) -> None:
        self.call("StartSession()")
        if home:
            self.call("Home()")

    def goto(self, point: object) -> None:
        x, y, z = (float(v) for v in point)  # type: ignore[attr-defined]
        self.call(f"GoTo(X({x:.6f}), Y({y:.6f}), Z({z:.6f}))")

    def ptmeas(self, nominal: object, ijk: object | None = None) -> list[float]:
        """The numbers of PtMeas's report (X, Y, Z by default: the ball's centre)."""
        x, y, z = (float(v) for v in nominal)  # type: ignore[attr-defined]
        text = f"PtMeas(X({x:.6f}), Y({y:.6f}), Z({z:.6f})"
        if ijk is not None:
            i, j, k = (float(v) for v in ijk)  # type: ignore[attr-defined]
            text += f", IJK({i:.9f}, {j:.9f}, {k:.9f})"
        [data] = self.call(text + ")").data
        return numbers(data)

    def position(self) -> list[float]:
        [data] = self.call("Get(X(), Y(), Z())").data
        return numbers(data)

    def clear(self) -> None:
        self.call("ClearAllErrors()")


def numbers(data: str) -> list[float]:
    """The numbers of a data line, in order (strings skipped)."""
    data = re.sub(r'"[^"]*"', "", data)
    return [float(v) for v in re.findall(r"[+-]?(?:[0-9]+\.?[0-9]*|\.[0-9]+)(?:[Ee][+-]?[0-9]+)?", data)]
