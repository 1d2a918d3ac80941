"""CMM driver over any pyserial URL (a tty such as ``/dev/pts/N``, ``socket://127.0.0.1:PORT``, ``loop://``).

Speaks the line protocol of ``hilcal.protocols.cmm`` (modelled on I++ DME), one transaction at a time:
send ``TAG Command(...)``, expect ``TAG &``, any ``TAG # data``, then ``TAG %`` or ``TAG ! Error(...)``.

Robustness rules (see docs/protocols.md (CMM section)):

* Lines that carry no readable tag, or a malformed body under a tag other than ours, are garbage: skipped
  and logged (at most ``max_skipped_lines`` per transaction).
* A well-formed response under a tag we gave up on (after a timeout) is stale: skipped and logged with its
  data. A well-formed response under any other tag is a CmmProtocolError.
* No acknowledgement within ``ack_timeout_s``, no completion within the command's timeout, or a malformed
  line under our tag: the input is drained (logged) and the command resent under a new tag, at most
  ``max_retries`` times; then CmmTimeout / CmmProtocolError.
* ``! Error`` ends the transaction: CmmError, or ProbeMiss for "no touch" / "surface not found".
"""

from __future__ import annotations

import re
import time
from collections import deque
from dataclasses import dataclass

import numpy as np
import serial
import structlog
from pydantic import BaseModel, ConfigDict, Field

from drivers.cmm.base import (
    CmmConnectionError,
    CmmError,
    CmmInterface,
    CmmProtocolError,
    CmmTimeout,
    ProbeMiss,
    ProbingConfig,
)
from hilcal.protocols.cmm import (
    ENCODING,
    MAX_LINE_BYTES,
    MAX_SEARCH_DISTANCE_MM,
    NAME_PATTERN,
    NUMBER_PATTERN,
    PRINTABLE_MAX,
    PRINTABLE_MIN,
    PROBE_MISS_ERRORS,
    SEARCH_PROPERTY,
    STRING_PATTERN,
    TAG_MAX,
    TAG_MIN,
    TAG_PATTERN,
    TERMINATOR,
    Command,
    Marker,
)

log = structlog.get_logger(__name__)

MAX_NESTING = 8
LOG_BYTES = 4096
MAX_DISCARD_BYTES = 65536
"""Bound on one drain, so a line that never stops chattering cannot hold the driver."""


class SerialCmmConfig(BaseModel):
    """Transport settings: timeouts per phase, retries, and where Home leaves the probe."""

    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)

    baudrate: int = Field(default=115200, gt=0)
    ack_timeout_s: float = Field(default=1.0, gt=0, description="from sending a command to its '&'")
    command_timeout_s: float = Field(default=30.0, gt=0, description="from '&' to '%' for GoTo, PtMeas, ...")
    home_timeout_s: float = Field(default=300.0, gt=0, description="from '&' to '%' for Home")
    max_retries: int = Field(default=2, ge=0, description="resends after a timeout or a malformed response")
    max_skipped_lines: int = Field(default=32, ge=0, description="garbage/stale lines tolerated per transaction")
    poll_s: float = Field(default=0.02, gt=0, description="read granularity of the port")
    write_timeout_s: float = Field(default=2.0, gt=0)
    home_mm: tuple[float, float, float] = Field(default=(0.0, 0.0, 0.0), description="where Home leaves the probe, "
                                                "CMM frame (the first move starts there)")


# ---------------------------------------------------------------------- response parsing (driver side)


class GarbageLine(CmmProtocolError):
    """A line with no readable tag (not ASCII, or not starting with 5 digits and a space)."""

    def __init__(self, raw: bytes) -> None:
        super().__init__(f"garbage line {raw[:80]!r}")
        self.raw = raw


class MalformedResponse(CmmProtocolError):
    """A tagged line whose body is not a valid response."""

    def __init__(self, tag: str, raw: bytes, reason: str) -> None:
        super().__init__(f"malformed response for tag {tag}: {reason}: {raw[:80]!r}")
        self.tag = tag
        self.raw = raw
        self.reason = reason


Value = float | str | tuple


@dataclass(frozen=True)
class Item:
    """``Name(arg, ...)`` in a data or error body; args are numbers, strings or nested items."""

    name: str
    args: tuple[Value, ...]


@dataclass(frozen=True)
class Response:
    """One parsed response line."""

    tag: str
    marker: Marker
    items: tuple[Item, ...] = ()


_NON_PRINTABLE = re.compile(f"[^\\x{PRINTABLE_MIN:02x}-\\x{PRINTABLE_MAX:02x}]")
_LINE_RE = re.compile(rf"(?P<tag>{TAG_PATTERN}) (?P<body>.*)", re.DOTALL)
_TOKEN_RE = re.compile(
    rf"\s*(?:(?P<number>{NUMBER_PATTERN})|(?P<string>{STRING_PATTERN})|(?P<name>{NAME_PATTERN})|(?P<punct>[(),]))"
)


def _tokens(text: str) -> list[tuple[str, str]]:
    out: list[tuple[str, str]] = []
    pos = 0
    while pos < len(text):
        if text[pos:].isspace():
            break
        m = _TOKEN_RE.match(text, pos)
        if m is None:
            raise ValueError(f"unexpected character {text[pos]!r} at {pos}")
        kind = m.lastgroup
        assert kind is not None
        out.append((kind, m.group(kind)))
        pos = m.end()
    return out


def _parse_items(text: str) -> tuple[Item, ...]:
    """``Name(args), Name(args), ...`` -> items; ValueError on anything else."""
    toks = _tokens(text)
    pos = 0

    def expect(kind: str, value: str | None = None) -> str:
        nonlocal pos
        if pos >= len(toks) or toks[pos][0] != kind or (value is not None and toks[pos][1] != value):
            found = toks[pos][1] if pos < len(toks) else "end of line"
            raise ValueError(f"expected {value or kind}, found {found!r}")
        pos += 1
        return toks[pos - 1][1]

    def item(depth: int) -> Item:
        nonlocal pos
        if depth > MAX_NESTING:
            raise ValueError("nesting too deep")
        name = expect("name")
        expect("punct", "(")
        args: list[Value] = []
        if pos < len(toks) and toks[pos] != ("punct", ")"):
            while True:
                kind, value = toks[pos] if pos < len(toks) else ("end", "")
                if kind == "number":
                    number = float(value)
                    if not np.isfinite(number):
                        raise ValueError(f"number out of range: {value}")
                    args.append(number)
                    pos += 1
                elif kind == "string":
                    args.append(value[1:-1])
                    pos += 1
                elif kind == "name":
                    args.append(item(depth + 1))
                else:
                    raise ValueError(f"expected an argument, found {value or 'end of line'!r}")
                if pos < len(toks) and toks[pos] == ("punct", ","):
                    pos += 1
                    continue
                break
        expect("punct", ")")
        return Item(name, tuple(args))

    items = [item(0)]
    while pos < len(toks):
        expect("punct", ",")
        items.append(item(0))
    return tuple(items)


def parse_response_line(raw: bytes) -> Response:
    """Parse one response line (terminator removed). Raises GarbageLine or MalformedResponse, nothing else."""
    try:
        text = raw.decode(ENCODING)
    except UnicodeDecodeError:
        raise GarbageLine(raw) from None
    m = _LINE_RE.fullmatch(text)
    if m is None:
        raise GarbageLine(raw)
    tag, body = m.group("tag"), m.group("body")
    if _NON_PRINTABLE.search(body):
        raise MalformedResponse(tag, raw, "non-printable character")
    if body in (Marker.ACK, Marker.DONE):
        return Response(tag, Marker(body))
    marker, sep, rest = body.partition(" ")
    if marker not in (Marker.DATA, Marker.ERROR) or not sep:
        raise MalformedResponse(tag, raw, "unknown response marker")
    try:
        items = _parse_items(rest)
    except (ValueError, IndexError, OverflowError) as err:
        raise MalformedResponse(tag, raw, str(err)) from None
    if marker == Marker.ERROR:
        err_item = items[0]
        ok = (
            len(items) == 1
            and err_item.name == "Error"
            and len(err_item.args) == 4
            and all(isinstance(a, float) and a == int(a) and a >= 0 for a in err_item.args[:2])
            and all(isinstance(a, str) for a in err_item.args[2:])
        )
        if not ok:
            raise MalformedResponse(tag, raw, "error body is not Error(severity, code, method, text)")
    return Response(tag, Marker(marker), items)


def error_from_response(resp: Response) -> CmmError:
    """The CmmError (ProbeMiss for a miss) carried by an ``!`` response."""
    severity, code, method, text = resp.items[0].args
    cls = ProbeMiss if int(code) in PROBE_MISS_ERRORS else CmmError
    return cls(int(code), str(text), int(severity), str(method))


def _xyz(items: tuple[Item, ...]) -> np.ndarray:
    values = {it.name: it.args for it in items}
    try:
        point = [values[axis] for axis in ("X", "Y", "Z")]
    except KeyError:
        raise CmmProtocolError(f"PtMeas data lacks X, Y or Z: {items}") from None
    if any(len(v) != 1 or not isinstance(v[0], float) for v in point):
        raise CmmProtocolError(f"PtMeas data is not X(x), Y(y), Z(z): {items}")
    return np.array([v[0] for v in point])


def _num(value: float) -> str:
    return f"{float(value):.6f}"


class _Retryable(CmmProtocolError):
    """A protocol failure of our own transaction that a resend may cure."""


class SerialCmm(CmmInterface):
    """The CMM over pyserial. Construct with a URL; call ``start_session()`` and ``home()`` before probing."""

    def __init__(self, url: str, config: SerialCmmConfig | None = None, probing: ProbingConfig | None = None) -> None:
        self.url = url
        self.config = config or SerialCmmConfig()
        self.probing = probing or ProbingConfig()
        self._rx = bytearray()
        self._tag = TAG_MIN - 1
        self._abandoned: deque[str] = deque(maxlen=64)
        try:
            self._port = serial.serial_for_url(
                url,
                baudrate=self.config.baudrate,
                timeout=self.config.poll_s,
                write_timeout=self.config.write_timeout_s,
            )
        except (serial.SerialException, OSError, ValueError) as err:
            raise CmmConnectionError(f"cannot open CMM port {url!r}: {err}") from err
        log.info("cmm.opened", url=url)

    # ------------------------------------------------------------------ I/O

    def close(self) -> None:
        """Close the port (the session is not ended: call ``end_session()`` first if it should be)."""
        if self._port.is_open:
            self._port.close()
            log.info("cmm.closed", url=self.url)

    def _next_tag(self) -> str:
        self._tag = self._tag + 1 if self._tag < TAG_MAX else TAG_MIN
        return f"{self._tag:05d}"

    def _write(self, line: str) -> None:
        try:
            self._port.write(line.encode(ENCODING) + TERMINATOR)
        except serial.SerialTimeoutException as err:
            raise CmmTimeout(f"writing {line!r} timed out after {self.config.write_timeout_s} s") from err
        except (serial.SerialException, OSError) as err:
            raise CmmConnectionError(f"writing to {self.url!r} failed: {err}") from err

    def _fill(self) -> None:
        """Read what arrives within one poll interval into the receive buffer."""
        try:
            chunk = self._port.read(1)
            if chunk:
                waiting = self._port.in_waiting
                if waiting:
                    chunk += self._port.read(waiting)
        except (serial.SerialException, OSError) as err:
            raise CmmConnectionError(f"reading from {self.url!r} failed: {err}") from err
        self._rx += chunk

    def _read_line(self, deadline: float) -> bytes | None:
        """Next line without its terminator, or None at the deadline (a partial line stays buffered)."""
        while True:
            end = self._rx.find(b"\n")
            if end >= 0:
                line = bytes(self._rx[:end]).removesuffix(b"\r")
                del self._rx[: end + 1]
                return line
            if len(self._rx) > MAX_LINE_BYTES + len(TERMINATOR):
                line = bytes(self._rx)
                self._rx.clear()
                return line
            if time.monotonic() >= deadline:
                return None
            self._fill()

    def _discard_input(self, reason: str) -> None:
        """Drop buffered and pending input, logging every byte of it."""
        pending = bytes(self._rx)
        self._rx.clear()
        try:
            while len(pending) < MAX_DISCARD_BYTES and self._port.in_waiting:
                pending += self._port.read(self._port.in_waiting)
        except (serial.SerialException, OSError) as err:
            raise CmmConnectionError(f"reading from {self.url!r} failed: {err}") from err
        if pending:
            log.warning(
                "cmm.input_discarded",
                reason=reason,
                n_bytes=len(pending),
                data=repr(pending[:LOG_BYTES]),
            )

    # ------------------------------------------------------------------ transactions

    def transact(self, command: str, completion_timeout_s: float | None = None) -> tuple[Response, ...]:
        """Send a command (without tag) and return its data responses; resends on timeout or garbling."""
        timeout = self.config.command_timeout_s if completion_timeout_s is None else completion_timeout_s
        attempts = 1 + self.config.max_retries
        last: CmmTimeout | _Retryable | None = None
        for attempt in range(1, attempts + 1):
            tag = self._next_tag()
            self._discard_input(f"before {tag}")
            log.debug("cmm.send", tag=tag, command=command, attempt=attempt)
            self._write(f"{tag} {command}")
            try:
                return self._await(tag, command, timeout)
            except (CmmTimeout, _Retryable) as err:
                self._abandoned.append(tag)
                log.warning("cmm.transaction_failed", tag=tag, command=command, attempt=attempt, error=str(err))
                last = err
        assert last is not None
        kind = CmmTimeout if isinstance(last, CmmTimeout) else CmmProtocolError
        raise kind(f"{command}: {last} (gave up after {attempts} attempts)") from last

    def _await(self, tag: str, command: str, completion_timeout_s: float) -> tuple[Response, ...]:
        deadline = time.monotonic() + self.config.ack_timeout_s
        acked = False
        data: list[Response] = []
        skipped = 0

        def skip(event: str, **kw: object) -> None:
            nonlocal skipped
            skipped += 1
            log.warning(event, waiting_for=tag, **kw)
            if skipped > self.config.max_skipped_lines:
                raise _Retryable(f"more than {self.config.max_skipped_lines} unusable lines while waiting for {tag}")

        while True:
            raw = self._read_line(deadline)
            if raw is None:
                phase = "completion" if acked else "acknowledgement"
                limit = completion_timeout_s if acked else self.config.ack_timeout_s
                partial = bytes(self._rx)
                raise CmmTimeout(
                    f"no {phase} of {tag} {command} within {limit} s"
                    + (f" (partial line {partial[:80]!r})" if partial else "")
                )
            try:
                resp = parse_response_line(raw)
            except GarbageLine:
                skip("cmm.garbage_skipped", raw=repr(raw[:LOG_BYTES]))
                continue
            except MalformedResponse as err:
                if err.tag == tag:
                    raise _Retryable(str(err)) from err
                skip("cmm.garbage_skipped", raw=repr(raw[:LOG_BYTES]))
                continue
            if resp.tag != tag:
                if resp.tag in self._abandoned:
                    skip("cmm.stale_response_skipped", raw=repr(raw))
                    continue
                raise CmmProtocolError(f"response {raw!r} has tag {resp.tag} while waiting for {tag} ({command})")
            if resp.marker is Marker.ACK:
                if not acked:
                    acked = True
                    deadline = time.monotonic() + completion_timeout_s
                continue
            if not acked:
                log.warning("cmm.response_before_ack", tag=tag, raw=repr(raw))
                acked = True
                deadline = time.monotonic() + completion_timeout_s
            if resp.marker is Marker.DATA:
                data.append(resp)
            elif resp.marker is Marker.DONE:
                return tuple(data)
            else:
                raise error_from_response(resp)

    # ------------------------------------------------------------------ commands

    def _start_session(self) -> None:
        self.transact(f"{Command.START_SESSION}()")

    def _set_search_distance(self, mm: float) -> None:
        if not 0 < mm <= MAX_SEARCH_DISTANCE_MM:
            raise ValueError(f"search distance must be in (0, {MAX_SEARCH_DISTANCE_MM}] mm, got {mm}")
        self.transact(f"{Command.SET_PROP}({SEARCH_PROPERTY}({_num(mm)}))")

    def end_session(self) -> None:
        self.transact(f"{Command.END_SESSION}()")

    def _home(self) -> np.ndarray:
        self.transact(f"{Command.HOME}()", self.config.home_timeout_s)
        return np.array(self.config.home_mm, dtype=float)

    def clear_errors(self) -> None:
        self.transact(f"{Command.CLEAR_ALL_ERRORS}()")

    def get_error_info(self, code: int) -> str:
        """The CMM's text for an error code."""
        data = self.transact(f"{Command.GET_ERROR_INFO}({int(code)})")
        for resp in data:
            for it in resp.items:
                if it.name == "ErrorInfo" and len(it.args) == 2 and isinstance(it.args[1], str):
                    return it.args[1]
        raise CmmProtocolError(f"GetErrorInfo({code}) returned no ErrorInfo(code, text): {data}")

    def _goto(self, point_mm: np.ndarray) -> None:
        p = _finite3(point_mm, "point_mm")
        self.transact(f"{Command.GO_TO}(X({_num(p[0])}), Y({_num(p[1])}), Z({_num(p[2])}))")

    def _probe(self, point_mm: np.ndarray, ijk: np.ndarray) -> np.ndarray:
        p = _finite3(point_mm, "point_mm")
        n = _finite3(ijk, "ijk")
        norm = np.linalg.norm(n)
        if norm == 0:
            raise ValueError("ijk must be a non-zero direction")
        n = n / norm
        data = self.transact(
            f"{Command.PT_MEAS}(X({_num(p[0])}), Y({_num(p[1])}), Z({_num(p[2])}), "
            f"IJK({_num(n[0])}, {_num(n[1])}, {_num(n[2])}))"
        )
        if len(data) != 1:
            raise CmmProtocolError(f"PtMeas returned {len(data)} data lines, expected 1")
        point = _xyz(data[0].items)
        log.debug("cmm.touch", target_mm=p.tolist(), point_mm=point.tolist())
        return point


def _finite3(value: np.ndarray, name: str) -> np.ndarray:
    v = np.asarray(value, dtype=float)
    if v.shape != (3,) or not np.all(np.isfinite(v)):
        raise ValueError(f"{name} must be 3 finite numbers, got {value!r}")
    return v
