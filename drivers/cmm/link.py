"""I++ DME transactions over any pyserial URL: ``socket://host:1294`` (the standard's transport, 6.1; a URL without
a port gets 1294), a tty, a pty. Tags and E-tags (6.2.1), transactions complete only at ``%`` (6.2.3), several errors
in one transaction (8), unsolicited E0000 lines at any time (6.2.4, 9.5), daemons' data after their ``%``.

One thread reads and writes; every wait is bounded and dispatches every line that arrives, whatever its tag:

* a line of a pending transaction updates it (``&``, ``#``, ``!``, ``%``); ``!`` never ends one, ``%`` does;
* E0000 is a server event: an error of severity 2 or more (an emergency stop, 0500) puts the link in the error
  state and is raised by the transaction waited on (after its ``%``) or by the next command; data (9.5: KeyPress,
  GoTo, PtMeas, ChangeTool, SetProp) are kept in ``events`` for the driver;
* a line under a tag given up on (a query asked again) is stale: logged, skipped; a malformed line is logged and
  skipped, and marks its transaction garbled when it carries that transaction's tag; more than
  ``max_skipped_lines`` such lines in one wait end the wait (``LinkGarbled``).

After an error of severity 2 or more only GetErrStatusE, GetXtdErrStatus and ClearAllErrors are sent (6.2.5; and
``ALLOWED_IN_ERROR``), after AbortE only ClearAllErrors (6.3.1.5), until a ClearAllErrors (or a StartSession, which
implies one, 6.3.1.1) completes cleanly; anything else raises ``CmmInErrorState`` without being written. Queries
that move nothing (``RE_ASKABLE``) are asked again under a new tag after a timeout; nothing else is ever sent twice
here (a motion's timeout is the driver's to recover with AbortE, ``drivers.cmm.ippdme``). Every line sent and
received goes to the transcript sink as it is.
"""

from __future__ import annotations

import select
import time
from collections import deque
from dataclasses import dataclass, field
from urllib.parse import urlsplit

import serial
import structlog
from pydantic import BaseModel, ConfigDict, Field

from drivers.cmm.forms import Kind, Note, check_response
from drivers.cmm.transcript import RECEIVED, SENT, TranscriptSink, printable
from drivers.cmm.types import (
    CmmCollision,
    CmmConnectionError,
    CmmEmergencyStop,
    CmmError,
    CmmInErrorState,
    CmmProtocolError,
    CmmTimeout,
    CmmTransactionAborted,
    ErrorReport,
    ProbeMiss,
)
from drivers.cmm.wire import (
    Arg,
    Item,
    LineSyntaxError,
    ResponseLine,
    check_command,
    command_line,
    format_tag,
    parse_response,
)
from hilcal.protocols.ippdme import (
    DEFAULT_TCP_PORT,
    ENCODING,
    EVENT_METHODS,
    MAX_LINE_CHARS,
    NEEDS_CLEAR,
    PROBE_MISS_CODES,
    TERMINATOR,
    WHILE_IN_ERROR_METHODS,
    Code,
    Marker,
    Method,
)

log = structlog.get_logger(__name__)

RE_ASKABLE = frozenset({
    Method.GET, Method.GET_PROP, Method.GET_PROP_E, Method.IS_HOMED, Method.IS_USER_ENABLED, Method.GET_DME_VERSION,
    Method.GET_MACHINE_CLASS, Method.ENUM_TOOLS, Method.ENUM_PROP, Method.ENUM_ALL_PROP, Method.GET_ERROR_INFO,
    Method.GET_ERR_STATUS_E, Method.GET_XTD_ERR_STATUS, Method.GET_COORD_SYSTEM, Method.GET_CSY_TRANSFORMATION,
    Method.GET_CHANGE_TOOL_ACTION, Method.SET_PROP, Method.ON_PT_MEAS_REPORT, Method.SET_COORD_SYSTEM,
    Method.CLEAR_ALL_ERRORS, Method.END_SESSION,
})
"""Commands that move nothing and change nothing a second time (queries; settings to the same value; ClearAllErrors;
EndSession, which does nothing without a session, 6.3.1): asked again under a new tag after a timeout."""
MAX_RESPONSE_BYTES = MAX_LINE_CHARS + len(TERMINATOR)
ALLOWED_IN_ERROR = WHILE_IN_ERROR_METHODS | {Method.ABORT_E, Method.START_SESSION, Method.END_SESSION}
"""Sent in the error state: the three of 6.2.5, AbortE (it stops motion), and the session commands (outside a session
the server takes nothing else, so ClearAllErrors cannot clear there; EndSession then StartSession "will start a new
session in any case", 6.3.1, and StartSession implies ClearAllErrors, 6.3.1.1)."""


class LinkConfig(BaseModel):
    """Timing of the link: every wait is bounded by one of these."""

    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)

    baudrate: int = Field(default=115200, gt=0, description="a serial line's speed (ignored on TCP)")
    ack_timeout_s: float = Field(default=2.0, gt=0, description="from sending a command to its '&'")
    query_timeout_s: float = Field(default=10.0, gt=0, description="from '&' to '%' of a command that moves nothing")
    query_retries: int = Field(default=2, ge=0, le=5, description="re-asks of a query after a timeout")
    abort_timeout_s: float = Field(default=10.0, gt=0, description="from AbortE to its '%'")
    max_skipped_lines: int = Field(default=32, ge=0, description="unusable lines tolerated in one wait")
    poll_s: float = Field(default=0.02, gt=0, description="read granularity of a port without a descriptor to wait "
                          "on (a pty, a tty and TCP have one)")
    write_timeout_s: float = Field(default=2.0, gt=0)


class LinkTimeout(CmmTimeout):
    """No ``&`` (phase "ack") or no ``%`` (phase "completion") of a transaction within its wait."""

    def __init__(self, message: str, tx: Transaction, phase: str) -> None:
        super().__init__(message)
        self.tx = tx
        self.phase = phase


class LinkGarbled(CmmProtocolError):
    """More unusable lines than ``max_skipped_lines`` in one wait."""


class CommandRefused(CmmProtocolError):
    """A command line the driver will not send: it breaks the syntax of 6.1.4.2 (nothing was written)."""


@dataclass(eq=False)
class Transaction:
    """One command and what came back under its tag."""

    tag: str
    line: str
    method: str
    acked: bool = False
    done: bool = False
    data: list[ResponseLine] = field(default_factory=list)
    errors: list[ErrorReport] = field(default_factory=list)
    unsolicited: list[ErrorReport] = field(default_factory=list)
    """E0000 errors of severity 2 or more that arrived while it was pending."""
    garbled: list[str] = field(default_factory=list)
    """Malformed lines that carried its tag."""

    @property
    def warnings(self) -> list[ErrorReport]:
        """Its errors of severity 0 and 1 (8.1: they do not interfere): returned, not raised."""
        return [e for e in self.errors if e.severity < NEEDS_CLEAR]


@dataclass(frozen=True)
class ServerEvent:
    """An E0000 line (6.2.4, 9.5): an unsolicited error or a server event's data."""

    line: ResponseLine
    received_s: float

    @property
    def kind(self) -> str:
        """``error`` or the server event's name (9.5: KeyPress, GoTo, PtMeas, ChangeTool, SetProp)."""
        if self.line.error is not None:
            return "error"
        first = self.line.values[0] if self.line.values else None
        return first.name if isinstance(first, Item) else "data"

    @property
    def error(self) -> CmmError | None:
        """The typed error of an unsolicited error line (None for data)."""
        e = self.line.error
        if e is None:
            return None
        report = ErrorReport(e.severity, e.code, e.method, e.text, self.line.tag)
        return error_class(e.code)(e.code, e.text, e.severity, e.method, self.line.tag, (report,))


def normalise_url(url: str) -> str:
    """A ``socket://host`` URL without a port gets the I++ DME application port 1294 (6.1)."""
    parts = urlsplit(url)
    if parts.scheme == "socket" and parts.port is None and parts.hostname:
        return url.replace(f"socket://{parts.netloc}", f"socket://{parts.netloc}:{DEFAULT_TCP_PORT}", 1)
    return url


def error_class(code: int) -> type[CmmError]:
    """The typed error of an error number."""
    if code == Code.EMERGENCY_STOP:
        return CmmEmergencyStop
    if code == Code.COLLISION:
        return CmmCollision
    if code == Code.TRANSACTION_ABORTED:
        return CmmTransactionAborted
    if code in PROBE_MISS_CODES:
        return ProbeMiss
    return CmmError


def raise_for(reports: list[ErrorReport], errors: tuple[ErrorReport, ...]) -> CmmError:
    """The error to raise for these reports of severity 2 or more: an emergency stop first, then a collision, then
    the first that is not 0006 (the abort is a consequence), else the first."""
    ranked = sorted(reports, key=lambda e: (e.code != Code.EMERGENCY_STOP, e.code != Code.COLLISION,
                                            e.code == Code.TRANSACTION_ABORTED))
    e = ranked[0]
    return error_class(e.code)(e.code, e.text, e.severity, e.method, e.tag, errors)


class IppLink:
    """The transaction layer of one connection (see the module docstring). Not thread-safe."""

    def __init__(self, url: str, config: LinkConfig | None = None, transcript: TranscriptSink | None = None) -> None:
        self.url = normalise_url(url)
        self.config = config or LinkConfig()
        self.transcript = transcript
        self._rx = bytearray()
        self._tag = 0
        self._etag = 0
        self.pending: dict[str, Transaction] = {}
        self.abandoned: deque[str] = deque(maxlen=64)
        self.daemons: set[str] = set()
        self.events: deque[ServerEvent] = deque(maxlen=256)
        self.events_total = 0
        """Events received since the link opened (the driver counts which it has seen)."""
        self.reports: deque[ResponseLine] = deque(maxlen=1024)
        """Daemons' data (OnMoveReportE) that came after their ``%``."""
        self.error_state: CmmError | None = None
        self.abort_pending = False
        self._seen_notes: set[str] = set()
        try:
            self._port = serial.serial_for_url(self.url, baudrate=self.config.baudrate, timeout=0,
                                               write_timeout=self.config.write_timeout_s)
        except (serial.SerialException, OSError, ValueError, TypeError) as err:
            raise CmmConnectionError(f"cannot open CMM port {self.url!r}: {err}") from err
        try:
            self._fd: int | None = self._port.fileno()
        except (AttributeError, NotImplementedError, OSError, ValueError, serial.SerialException):
            self._fd = None
        log.info("cmm.opened", url=self.url)

    def close(self) -> None:
        """Close the port (a session is not ended here)."""
        if self._port.is_open:
            self._port.close()
            log.info("cmm.closed", url=self.url)

    # ------------------------------------------------------------------ tags and sending

    def next_tag(self, event: bool = False) -> str:
        """The next free command tag (00001..99999) or E-tag (E0001..E9999), skipping those still in use."""
        for _ in range(100000):
            if event:
                self._etag = self._etag % 9999 + 1
                tag = format_tag(self._etag, event=True)
            else:
                self._tag = self._tag % 99999 + 1
                tag = format_tag(self._tag)
            if tag not in self.pending and tag not in self.abandoned and tag not in self.daemons:
                return tag
        raise CmmProtocolError("no free tag")

    def send(self, method: str, *args: Arg, tag: str | None = None) -> Transaction:
        """Check and write ``TAG Method(args)`` (an E-tag for the fast-queue methods); the pending transaction."""
        tag = tag or self.next_tag(event=method in EVENT_METHODS)
        try:
            line = command_line(tag, method, *args)
        except (LineSyntaxError, ValueError) as err:
            raise CommandRefused(f"{method}: {err}") from err
        return self._send_line(tag, method, line)

    def send_text(self, text: str, tag: str) -> Transaction:
        """Write a command given as text (``GoTo(X(1))``) under this tag, after the checks of ``send``."""
        line = f"{tag} {text}"
        try:
            check_command(line)
        except LineSyntaxError as err:
            raise CommandRefused(str(err)) from err
        return self._send_line(tag, text.split("(", 1)[0].strip(), line)

    def _send_line(self, tag: str, method: str, line: str) -> Transaction:
        self.poll()
        if self.abort_pending and method != Method.CLEAR_ALL_ERRORS:
            raise CmmInErrorState(f"{method} not sent: after AbortE the next command is ClearAllErrors (6.3.1.5)",
                                  self.error_state)
        if self.error_state is not None and method not in ALLOWED_IN_ERROR:
            raise CmmInErrorState(f"{method} not sent: the CMM is in an error state until ClearAllErrors (6.2.5): "
                                  f"{self.error_state}", self.error_state)
        if tag in self.pending:
            raise CmmProtocolError(f"tag {tag} is still in use (6.2.1: tags are unique while pending)")
        tx = Transaction(tag, line, method)
        self.pending[tag] = tx
        self._write(line)
        return tx

    def _write(self, line: str) -> None:
        if self.transcript is not None:
            self.transcript.write(SENT, line)
        try:
            self._port.write(line.encode(ENCODING) + TERMINATOR)
        except serial.SerialTimeoutException as err:
            raise CmmTimeout(f"writing {line!r} timed out after {self.config.write_timeout_s} s") from err
        except (serial.SerialException, OSError) as err:
            raise CmmConnectionError(f"writing to {self.url!r} failed: {err}") from err
        log.debug("cmm.sent", line=line)

    # ------------------------------------------------------------------ waiting

    def wait(self, tx: Transaction, timeout_s: float, ack_timeout_s: float | None = None) -> Transaction:
        """Dispatch lines until ``tx`` completes: its ``&`` within ``ack_timeout_s`` (default the config's), its ``%``
        within ``timeout_s`` of the ``&``. LinkTimeout otherwise (``tx`` stays pending)."""
        ack_limit = self.config.ack_timeout_s if ack_timeout_s is None else ack_timeout_s
        deadline = time.monotonic() + ack_limit
        acked, skipped = tx.acked, 0
        if acked:
            deadline = time.monotonic() + timeout_s
        while not tx.done:
            raw = self._read_line(deadline)
            if raw is None:
                phase, limit = ("completion", timeout_s) if tx.acked else ("ack", ack_limit)
                partial = f" (a partial line {bytes(self._rx[:80])!r})" if self._rx else ""
                raise LinkTimeout(f"no {'%' if tx.acked else '&'} of {tx.line!r} within {limit} s{partial}", tx, phase)
            skipped += not self._dispatch(raw)
            if skipped > self.config.max_skipped_lines:
                raise LinkGarbled(f"more than {self.config.max_skipped_lines} unusable lines while waiting for "
                                  f"{tx.line!r}")
            if tx.acked and not acked:
                acked, deadline = True, time.monotonic() + timeout_s
        return tx

    def poll(self) -> None:
        """Dispatch every complete line that has already arrived (events between transactions)."""
        while True:
            raw = self._read_line(time.monotonic(), block=False)
            if raw is None:
                return
            self._dispatch(raw)

    def _fill(self, wait_s: float) -> None:
        """Wait up to ``wait_s`` for input (select on the port's descriptor where it has one, else a poll interval)
        and take in all that has arrived."""
        try:
            if self._fd is not None:
                ready, _, _ = select.select([self._fd], [], [], max(wait_s, 0.0))
                if not ready:
                    return
            elif wait_s > 0:
                time.sleep(min(wait_s, self.config.poll_s))
            while chunk := self._port.read(65536):
                self._rx += chunk
        except (serial.SerialException, OSError, ValueError) as err:
            raise CmmConnectionError(f"reading from {self.url!r} failed: {err}") from err

    def _read_line(self, deadline: float, block: bool = True) -> bytes | None:
        """The next line without its terminator, or None at the deadline (a partial line stays buffered); without
        ``block`` only what has already arrived."""
        filled = False
        while True:
            end = self._rx.find(b"\n")
            if end >= 0:
                line = bytes(self._rx[:end])
                del self._rx[:end + 1]
                if line.endswith(b"\r"):
                    return line[:-1]
                self.note(Note(Kind.NONCONFORMANT, "a line ended by LF alone (6.1.1: CR LF always as a pair)"), "")
                return line
            if len(self._rx) > MAX_RESPONSE_BYTES:
                line = bytes(self._rx)
                self._rx.clear()
                return line
            left = deadline - time.monotonic()
            if (not block and filled) or (block and left <= 0):
                return None
            self._fill(left if block else 0.0)
            filled = True

    def discard_partial(self) -> None:
        """Drop a partial line (after a timeout): it goes to the transcript and the log as it came."""
        if self._rx:
            raw = bytes(self._rx)
            self._rx.clear()
            if self.transcript is not None:
                self.transcript.write(RECEIVED, printable(raw))
            log.warning("cmm.partial_line_discarded", raw=printable(raw[:4096]))

    # ------------------------------------------------------------------ dispatching

    def _dispatch(self, raw: bytes) -> bool:
        """Handle one received line; False when it was unusable (malformed, stale, unexpected)."""
        text = printable(raw)
        if self.transcript is not None:
            self.transcript.write(RECEIVED, text)
        try:
            line = parse_response(raw.decode(ENCODING))
        except (UnicodeDecodeError, LineSyntaxError) as err:
            reason = err.reason if isinstance(err, LineSyntaxError) else "bytes outside ASCII (6.1.1)"
            tx = self.pending.get(text[:5])
            if tx is not None:
                tx.garbled.append(text)
            log.warning("cmm.malformed_line", raw=text[:4096], reason=reason, tag=text[:5] if tx else None)
            return False
        for note in check_response(line):
            self.note(note, line.raw)
        if line.is_server_event:
            self._event(line)
            return True
        tx = self.pending.get(line.tag)
        if tx is not None:
            self._update(tx, line)
            return True
        if line.tag in self.daemons and line.marker is Marker.DATA:
            self.reports.append(line)
            return True
        if line.tag in self.abandoned:
            log.info("cmm.stale_response", line=line.raw)
            return False
        log.warning("cmm.unexpected_response", line=line.raw, pending=list(self.pending))
        return False

    def _update(self, tx: Transaction, line: ResponseLine) -> None:
        if line.marker is Marker.ACK:
            if tx.acked:
                self.note(Note(Kind.NONCONFORMANT, "a second '&' in one transaction (6.2.3)"), line.raw)
            tx.acked = True
            return
        if not tx.acked:
            self.note(Note(Kind.NONCONFORMANT, f"'{line.marker.value}' before the transaction's '&' (6.2.3)"),
                       line.raw)
            tx.acked = True
        if line.marker is Marker.DATA:
            tx.data.append(line)
        elif line.marker is Marker.ERROR and line.error is not None:
            e = line.error
            tx.errors.append(ErrorReport(e.severity, e.code, e.method, e.text, line.tag))
        else:
            tx.done = True
            del self.pending[tx.tag]
            self._completed(tx)

    def _completed(self, tx: Transaction) -> None:
        serious = [e for e in tx.errors if e.severity >= NEEDS_CLEAR]
        if serious:
            self.error_state = raise_for(serious, tuple(tx.errors))
        elif tx.method in (Method.CLEAR_ALL_ERRORS, Method.START_SESSION) and not tx.garbled:
            self.error_state, self.abort_pending = None, False
        if tx.method == Method.ABORT_E:
            self.abort_pending = True
        if tx.method == Method.ON_MOVE_REPORT_E and not serious:
            self.daemons.add(tx.tag)
        elif tx.method in (Method.STOP_ALL_DAEMONS, Method.END_SESSION, Method.START_SESSION):
            self.daemons.clear()
        elif tx.method == Method.STOP_DAEMON:
            self.daemons.discard(tx.line.rsplit("(", 1)[-1].rstrip(") "))

    def _event(self, line: ResponseLine) -> None:
        self.events.append(ServerEvent(line, time.monotonic()))
        self.events_total += 1
        e = line.error
        if e is None:
            log.info("cmm.event", line=line.raw)
            return
        report = ErrorReport(e.severity, e.code, e.method, e.text, line.tag)
        if e.severity < NEEDS_CLEAR:
            log.warning("cmm.warning", tag=line.tag, code=e.code, severity=e.severity, text=e.text, method=e.method)
            return
        log.error("cmm.unsolicited_error", code=e.code, severity=e.severity, text=e.text, method=e.method)
        self.error_state = raise_for([report], (report,))
        for tx in self.pending.values():
            tx.unsolicited.append(report)

    def note(self, note: Note, raw: str) -> None:
        """Log a note on a received line: problems and nonconformities at warning the first time, the rest quietly."""
        first = note.text not in self._seen_notes
        self._seen_notes.add(note.text)
        quiet = note.kind in (Kind.VERSION, Kind.EXTENSION) or not first
        (log.debug if quiet else log.warning)("cmm.nonconformant", kind=str(note.kind), note=note.text, line=raw)

    # ------------------------------------------------------------------ outcomes

    def outcome(self, tx: Transaction) -> Transaction:
        """The completed transaction, its warnings logged; the typed CmmError for its errors of severity 2 or more
        (or for an unsolicited one that came while it was pending); CmmProtocolError when a line of it was garbled."""
        for w in tx.warnings:
            log.warning("cmm.warning", tag=tx.tag, command=tx.line, code=w.code, severity=w.severity, text=w.text)
        serious = [e for e in [*tx.errors, *tx.unsolicited] if e.severity >= NEEDS_CLEAR]
        if serious:
            raise raise_for(serious, (*tx.errors, *tx.unsolicited))
        if tx.garbled:
            raise CmmProtocolError(f"{tx.line}: malformed response line(s) {tx.garbled[:3]}")
        return tx

    def abandon(self, tx: Transaction) -> None:
        """Give up on a pending transaction: its late lines are stale."""
        self.pending.pop(tx.tag, None)
        self.abandoned.append(tx.tag)
        self.discard_partial()

    def transact(self, method: str, *args: Arg, timeout_s: float | None = None) -> Transaction:
        """Send, wait, ``outcome``; a command of ``RE_ASKABLE`` is asked again under a new tag after a timeout or a
        garbled answer, at most ``query_retries`` times. Anything else that times out raises LinkTimeout."""
        timeout = self.config.query_timeout_s if timeout_s is None else timeout_s
        attempts = 1 + (self.config.query_retries if method in RE_ASKABLE else 0)
        for attempt in range(1, attempts + 1):
            tx = self.send(method, *args)
            try:
                self.wait(tx, timeout)
                return self.outcome(tx)
            except (LinkTimeout, LinkGarbled) as err:
                if attempt == attempts:
                    raise
                self.abandon(tx)
                log.warning("cmm.query_asked_again", command=tx.line, attempt=attempt, error=str(err))
            except CmmProtocolError as err:
                if attempt == attempts or method not in RE_ASKABLE:
                    raise
                log.warning("cmm.query_asked_again", command=tx.line, attempt=attempt, error=str(err))
        raise AssertionError("unreachable")
