"""The simulated controller's CAN personality, served as an SLCAN (Lawicel ASCII) adapter.

``ControllerCanPeer`` speaks the frames of ``hilcal/protocols/controller.dbc`` (counter and checksum checked on
every received frame, set on every sent one). ``SlcanServer`` makes it look like a USB-serial CAN adapter on a
pseudo-terminal (or a TCP socket for pyserial's ``socket://`` URLs), so python-can's ``slcan`` interface and
the real driver code run unchanged. ``CanBusServer`` serves the same peer on any python-can bus (``virtual``
for fast tests). ``CanFaultInjector`` drops, corrupts, repeats and delays frames and silences the heartbeat.
Independent of ``drivers``: only the shared protocol data is imported.
"""

from __future__ import annotations

import contextlib
import errno
import heapq
import itertools
import os
import random
import select
import socket
import termios
import threading
import time
import tty
from collections import Counter
from dataclasses import dataclass, field
from typing import Any, Literal

import can
import cantools
import structlog

from hilcal.protocols import controller_dbc_text
from hilcal.protocols.checksums import (
    CAN_CHECKSUM_BYTE,
    CAN_COUNTER_BYTE,
    CAN_COUNTER_MODULO,
    CAN_PAYLOAD_BYTES,
    can_frame_checksum,
)
from hilcal.protocols.controller_states import Command, ControllerState, RefusalReason
from sim_devices.controller import CanFaultConfig, SimulatedController

log = structlog.get_logger(__name__)

Direction = Literal["tx", "rx"]
Frame = tuple[int, bytes]
UM_PER_MM = 1000
MAX_UM = (1 << 24) - 1
COUNTER_RESYNC_S = 1.0
"""A frame ID silent for longer than this accepts any counter value (a new host session)."""

# ---------------------------------------------------------------------------------------------- frame codec


class CanFrameError(ValueError):
    """A received frame that is not a valid controller frame."""


class UnknownFrameId(CanFrameError):
    pass


class BadFrameLength(CanFrameError):
    pass


class BadChecksum(CanFrameError):
    pass


class CanCodec:
    """Encode/decode controller frames with the shared DBC; counter and checksum are handled here."""

    def __init__(self) -> None:
        self.db = cantools.database.load_string(controller_dbc_text(), "dbc")
        self._by_id = {m.frame_id: m for m in self.db.messages}
        self._by_name = {m.name: m for m in self.db.messages}
        for m in self.db.messages:
            signals = {s.name: s for s in m.signals}
            counter, checksum = signals.get("Counter"), signals.get("Checksum")
            if (
                m.length != CAN_PAYLOAD_BYTES
                or counter is None
                or (counter.start, counter.length) != (CAN_COUNTER_BYTE * 8, 4)
                or checksum is None
                or (checksum.start, checksum.length) != (CAN_CHECKSUM_BYTE * 8, 8)
            ):
                raise ValueError(f"DBC message {m.name} does not follow the counter/checksum layout")

    def frame_id(self, name: str) -> int:
        return self._by_name[name].frame_id

    def senders(self, frame_id: int) -> list[str]:
        return list(self._by_id[frame_id].senders)

    def encode(self, name: str, signals: dict[str, int], counter: int) -> Frame:
        """Raw (unscaled) signal values -> (frame ID, 8 bytes) with counter and checksum set."""
        message = self._by_name[name]
        data = bytearray(message.encode({**signals, "Counter": counter % CAN_COUNTER_MODULO, "Checksum": 0},
                                        scaling=False))
        data[CAN_CHECKSUM_BYTE] = can_frame_checksum(message.frame_id, data)
        return message.frame_id, bytes(data)

    def decode(self, frame_id: int, data: bytes) -> tuple[str, dict[str, int]]:
        """(message name, raw signal values); raises a CanFrameError subclass for anything invalid."""
        message = self._by_id.get(frame_id)
        if message is None:
            raise UnknownFrameId(f"unknown frame ID 0x{frame_id:X}")
        if len(data) != message.length:
            raise BadFrameLength(f"{message.name}: {len(data)} data bytes, expected {message.length}")
        if data[CAN_CHECKSUM_BYTE] != can_frame_checksum(frame_id, data):
            raise BadChecksum(f"{message.name}: checksum mismatch")
        decoded = message.decode(bytes(data), decode_choices=False, scaling=False)
        return message.name, {k: int(v) for k, v in decoded.items()}


class CounterTracker:
    """Per-ID rolling-counter check: delta 0 = repeated (discard), delta n > 1 = n - 1 frames lost."""

    def __init__(self) -> None:
        self._last: dict[int, tuple[int, float]] = {}

    def reset(self) -> None:
        self._last.clear()

    def check(self, frame_id: int, counter: int, now: float) -> tuple[bool, int]:
        """(is_repeat, frames_lost) and remember this counter unless it is a repeat."""
        previous = self._last.get(frame_id)
        if previous is None or now - previous[1] > COUNTER_RESYNC_S:
            self._last[frame_id] = (counter, now)
            return False, 0
        delta = (counter - previous[0]) % CAN_COUNTER_MODULO
        if delta == 0:
            return True, 0
        self._last[frame_id] = (counter, now)
        return False, delta - 1


@dataclass
class PeerStats:
    """What the controller noticed on its CAN input."""

    rx_frames: int = 0
    rx_checksum_errors: int = 0
    rx_bad_length: int = 0
    rx_unknown_id: int = 0
    rx_ignored: int = 0
    rx_repeated: int = 0
    rx_lost: int = 0
    rx_by_name: Counter[str] = field(default_factory=Counter)
    tx_frames: int = 0


_SETPOINT_PAIRS = {"SetpointL12": 0, "SetpointL34": 1, "SetpointL56": 2}


STATE_POLL_S = 0.002
"""While a move is under way the server checks the state this often and sends Status at once on a change."""
WATCH_AFTER_SETPOINT_S = 0.5


class ControllerCanPeer:
    """The controller's CAN protocol: frames in -> model calls -> acknowledgement frames; heartbeat frames."""

    def __init__(self, controller: SimulatedController) -> None:
        self.controller = controller
        self.codec = CanCodec()
        self.stats = PeerStats()
        self._lock = threading.Lock()
        self._rx_counters = CounterTracker()
        self._tx_counters: Counter[str] = Counter()
        self._cycle = 0
        self._pending: dict[int, tuple[int, tuple[int, int]]] = {}
        self._fault_events_seen = controller.snapshot().fault_events
        self._state_sent: ControllerState | None = None
        self._watch_until = 0.0

    def status_changed(self) -> bool:
        """True when the controller's state differs from the last status sent (or a setpoint came since)."""
        return self.controller.snapshot().state != self._state_sent

    @property
    def watching(self) -> bool:
        """A move is (or may be) under way: a setpoint arrived recently or the last status said MOVING."""
        return self._state_sent == ControllerState.MOVING or time.monotonic() < self._watch_until

    def reset_session(self) -> None:
        """A new host session (SLCAN channel opened): forget received counters and partial setpoints."""
        with self._lock:
            self._rx_counters.reset()
            self._pending.clear()

    def _next_tx(self, name: str, signals: dict[str, int]) -> Frame:
        counter = self._tx_counters[name]
        self._tx_counters[name] = (counter + 1) % CAN_COUNTER_MODULO
        self.stats.tx_frames += 1
        return self.codec.encode(name, signals, counter)

    def _ack(self, command: int, reason: RefusalReason, request_counter: int) -> Frame:
        state = self.controller.snapshot().state
        signals = {"CommandCode": command, "Reason": int(reason), "State": int(state),
                   "RequestCounter": request_counter}
        return self._next_tx("CommandAck", signals)

    def handle_frame(self, frame_id: int, data: bytes, *, extended: bool = False, remote: bool = False) -> list[Frame]:
        """Process one received frame; returns the frames to send in answer (possibly none)."""
        with self._lock:
            self.stats.rx_frames += 1
            if extended or remote:
                self.stats.rx_ignored += 1
                return []
            try:
                name, signals = self.codec.decode(frame_id, data)
            except UnknownFrameId:
                self.stats.rx_unknown_id += 1
                return []
            except BadFrameLength:
                self.stats.rx_bad_length += 1
                return []
            except BadChecksum:
                self.stats.rx_checksum_errors += 1
                log.warning("can_rx_checksum_error", frame_id=hex(frame_id))
                return []
            if "HOST" not in self.codec.senders(frame_id):
                self.stats.rx_ignored += 1
                return []
            counter = signals["Counter"]
            repeated, lost = self._rx_counters.check(frame_id, counter, time.monotonic())
            self.stats.rx_lost += lost
            if repeated:
                self.stats.rx_repeated += 1
                return []
            self.stats.rx_by_name[name] += 1
            return self._dispatch(name, signals, counter)

    def _dispatch(self, name: str, signals: dict[str, int], counter: int) -> list[Frame]:
        if name == "EstopRequest":
            if signals["EstopActive"]:
                self.controller.press_estop(source="request")
            return []
        if name == "Command":
            code = signals["CommandCode"]
            try:
                command = Command(code)
            except ValueError:
                return [self._ack(code, RefusalReason.UNKNOWN_COMMAND, counter)]
            return [self._ack(code, self.controller.command(command), counter)]
        index = _SETPOINT_PAIRS[name]
        first, second = (v for k, v in signals.items() if k.endswith("Setpoint"))
        self._pending[index] = (counter, (first, second))
        if index < 2:
            return []
        parts = [self._pending.get(i) for i in range(3)]
        self._pending.clear()
        if any(p is None or p[0] != counter for p in parts):
            return [self._ack(Command.SETPOINT, RefusalReason.SETPOINT_INCOMPLETE, counter)]
        lengths_mm = [um / UM_PER_MM for p in parts if p is not None for um in p[1]]
        reason = self.controller.set_setpoint(lengths_mm, tag=counter)
        self._watch_until = time.monotonic() + WATCH_AFTER_SETPOINT_S
        self._state_sent = None
        return [self._ack(Command.SETPOINT, reason, counter)]

    def cycle_frames(self) -> list[Frame]:
        """One heartbeat: [FaultEvent if a fault happened,] Status, FeedbackL12, FeedbackL34, FeedbackL56."""
        with self._lock:
            snap = self.controller.snapshot()
            self._state_sent = snap.state
            frames = []
            if snap.fault_events != self._fault_events_seen:
                self._fault_events_seen = snap.fault_events
                frames.append(self._next_tx("FaultEvent", {"FaultCode": int(snap.fault), "State": int(snap.state),
                                                           "EstopInput": int(snap.estop_input)}))
            cycle = self._cycle
            self._cycle = (cycle + 1) % CAN_COUNTER_MODULO
            in_position = sum(1 << i for i, flag in enumerate(snap.in_position) if flag)
            status = {
                "State": int(snap.state),
                "EstopInput": int(snap.estop_input),
                "FaultCode": int(snap.fault),
                "InPosition": in_position,
                "SetpointCounter": snap.setpoint_tag % CAN_COUNTER_MODULO,
                "SetpointValid": int(snap.setpoint_valid),
            }
            frames.append(self.codec.encode("Status", status, cycle))
            um = [min(MAX_UM, max(0, round(v * UM_PER_MM))) for v in snap.lengths_mm]
            for k, name in enumerate(("FeedbackL12", "FeedbackL34", "FeedbackL56")):
                a, b = 2 * k + 1, 2 * k + 2
                frames.append(self.codec.encode(name, {f"Leg{a}Length": um[a - 1], f"Leg{b}Length": um[b - 1]}, cycle))
            self.stats.tx_frames += 4
            return frames


# ---------------------------------------------------------------------------------------------- fault injection


@dataclass
class _Rule:
    action: Literal["drop", "corrupt", "repeat", "delay"]
    direction: Direction
    frame_id: int | None
    remaining: int
    delay_s: float = 0.0


class CanFaultInjector:
    """Frame-level faults, switchable at start (CanFaultConfig) and at run time (the methods); thread-safe.

    "tx" frames are sent by the controller, "rx" frames are received by it. Rates apply to both directions,
    the constant delay to tx frames only; one-shot rules consume one count per matching frame.
    """

    def __init__(self, config: CanFaultConfig | None = None) -> None:
        cfg = config or CanFaultConfig()
        self._rng = random.Random(cfg.seed)
        self._lock = threading.Lock()
        self.drop_rate = cfg.drop_rate
        self.corrupt_rate = cfg.corrupt_rate
        self.repeat_rate = cfg.repeat_rate
        self.delay_s = cfg.delay_s
        self.heartbeat = cfg.heartbeat
        self._rules: list[_Rule] = []
        self.applied: Counter[str] = Counter()

    def _add(self, rule: _Rule) -> None:
        with self._lock:
            self._rules.append(rule)

    def drop_next(self, count: int = 1, *, frame_id: int | None = None, direction: Direction = "tx") -> None:
        self._add(_Rule("drop", direction, frame_id, count))

    def corrupt_next(self, count: int = 1, *, frame_id: int | None = None, direction: Direction = "tx") -> None:
        """Flip one (seeded random) bit of the next matching frames."""
        self._add(_Rule("corrupt", direction, frame_id, count))

    def repeat_next(self, count: int = 1, *, frame_id: int | None = None, direction: Direction = "tx") -> None:
        self._add(_Rule("repeat", direction, frame_id, count))

    def delay_next(self, delay_s: float, count: int = 1, *, frame_id: int | None = None) -> None:
        """Hold back the next matching controller frames (later frames overtake them)."""
        self._add(_Rule("delay", "tx", frame_id, count, delay_s))

    def set_heartbeat(self, enabled: bool) -> None:
        """False: the controller stops sending Status/Feedback (a lost heartbeat)."""
        self.heartbeat = enabled

    def clear(self) -> None:
        """Remove all one-shot rules and rates (the heartbeat switch is left as it is)."""
        with self._lock:
            self._rules.clear()
            self.drop_rate = self.corrupt_rate = self.repeat_rate = self.delay_s = 0.0

    def _take(self, action: str, direction: Direction, frame_id: int) -> _Rule | None:
        for rule in self._rules:
            if rule.action == action and rule.direction == direction and rule.frame_id in (None, frame_id):
                rule.remaining -= 1
                if rule.remaining <= 0:
                    self._rules.remove(rule)
                return rule
        return None

    def apply(self, direction: Direction, frame_id: int, data: bytes) -> list[tuple[float, bytes]]:
        """The copies of a frame that actually go through, each with its extra delay in seconds."""
        with self._lock:
            if self._take("drop", direction, frame_id) or self._rng.random() < self.drop_rate:
                self.applied["drop"] += 1
                return []
            if data and (self._take("corrupt", direction, frame_id) or self._rng.random() < self.corrupt_rate):
                self.applied["corrupt"] += 1
                bit = self._rng.randrange(8 * len(data))
                mutable = bytearray(data)
                mutable[bit // 8] ^= 1 << (bit % 8)
                data = bytes(mutable)
            delay = self.delay_s if direction == "tx" else 0.0
            rule = self._take("delay", direction, frame_id)
            if rule is not None:
                self.applied["delay"] += 1
                delay += rule.delay_s
            copies = [(delay, data)]
            if self._take("repeat", direction, frame_id) or self._rng.random() < self.repeat_rate:
                self.applied["repeat"] += 1
                copies.append((delay, data))
            return copies


class _Outbox:
    """Frames to send now or later (fault-injected delays), ordered by due time."""

    def __init__(self, faults: CanFaultInjector) -> None:
        self.faults = faults
        self._heap: list[tuple[float, int, int, bytes]] = []
        self._seq = itertools.count()

    def schedule(self, frames: list[Frame], now: float) -> list[Frame]:
        """Apply tx faults; return the frames due now and keep the delayed ones."""
        immediate = []
        for frame_id, data in frames:
            for delay, copy in self.faults.apply("tx", frame_id, data):
                if delay > 0:
                    heapq.heappush(self._heap, (now + delay, next(self._seq), frame_id, copy))
                else:
                    immediate.append((frame_id, copy))
        return immediate

    def due(self, now: float) -> list[Frame]:
        out = []
        while self._heap and self._heap[0][0] <= now:
            _, _, frame_id, data = heapq.heappop(self._heap)
            out.append((frame_id, data))
        return out

    def next_due(self) -> float | None:
        return self._heap[0][0] if self._heap else None

    def clear(self) -> None:
        self._heap.clear()


# ---------------------------------------------------------------------------------------------- SLCAN parsing


class SlcanError(ValueError):
    """A line that is not a valid SLCAN command (answered with BEL)."""


@dataclass(frozen=True)
class SlcanCommand:
    """One parsed SLCAN line; frame fields are set for t/T/r/R."""

    code: str
    argument: str = ""
    frame_id: int | None = None
    data: bytes = b""
    extended: bool = False
    remote: bool = False


MAX_LINE_BYTES = 64
_HEX = frozenset("0123456789abcdefABCDEF")
_NO_ARGUMENT = frozenset("OCLVvNF")


def _hex(text: str, what: str) -> int:
    if not text or not set(text) <= _HEX:
        raise SlcanError(f"{what}: {text!r} is not hexadecimal")
    return int(text, 16)


def parse_slcan_line(line: bytes) -> SlcanCommand:
    """Parse one line (without its CR) sent by a host to an SLCAN adapter."""
    try:
        text = line.decode("ascii")
    except UnicodeDecodeError:
        raise SlcanError("non-ASCII bytes") from None
    if not text.isprintable():
        raise SlcanError("control characters in line")
    if not text:
        return SlcanCommand("")
    code, arg = text[0], text[1:]
    if code in "tTrR":
        id_digits = 8 if code in "TR" else 3
        if len(arg) < id_digits + 1:
            raise SlcanError(f"frame line too short: {text!r}")
        frame_id = _hex(arg[:id_digits], "identifier")
        if frame_id > (0x1FFFFFFF if id_digits == 8 else 0x7FF):
            raise SlcanError(f"identifier 0x{frame_id:X} out of range")
        dlc_char = arg[id_digits]
        if dlc_char not in "012345678":
            raise SlcanError(f"DLC {dlc_char!r} is not 0..8")
        dlc = int(dlc_char)
        payload = arg[id_digits + 1:]
        remote = code in "rR"
        if remote:
            if payload:
                raise SlcanError("remote frame with data")
            data = b""
        else:
            if len(payload) != 2 * dlc:
                raise SlcanError(f"{len(payload)} data digits for DLC {dlc}")
            if not set(payload) <= _HEX:
                raise SlcanError("data is not hexadecimal")
            data = bytes.fromhex(payload)
        return SlcanCommand(code, arg, frame_id, data, extended=code in "TR", remote=remote)
    if code in _NO_ARGUMENT:
        if arg:
            raise SlcanError(f"command {code!r} takes no argument")
        return SlcanCommand(code)
    if code == "S":
        if len(arg) != 1 or arg not in "012345678":
            raise SlcanError(f"bitrate code {arg!r} is not 0..8")
        return SlcanCommand(code, arg)
    if code == "s":
        if len(arg) != 4:
            raise SlcanError("BTR needs 4 hex digits")
        _hex(arg, "BTR")
        return SlcanCommand(code, arg)
    if code in "ZX":
        if arg not in ("0", "1"):
            raise SlcanError(f"{code} needs 0 or 1")
        return SlcanCommand(code, arg)
    if code in "Mm":
        if len(arg) != 8:
            raise SlcanError("acceptance code/mask needs 8 hex digits")
        _hex(arg, "acceptance")
        return SlcanCommand(code, arg)
    raise SlcanError(f"unsupported command {code!r}")


class SlcanLineSplitter:
    """Split a byte stream into CR-terminated lines; overlong lines become SlcanError items."""

    def __init__(self, max_line_bytes: int = MAX_LINE_BYTES) -> None:
        self._buffer = bytearray()
        self._max = max_line_bytes
        self._overflow = False

    def feed(self, data: bytes) -> list[bytes | SlcanError]:
        self._buffer.extend(data)
        out: list[bytes | SlcanError] = []
        while True:
            end = self._buffer.find(b"\r")
            if end < 0:
                if len(self._buffer) > self._max:
                    self._buffer.clear()
                    self._overflow = True
                return out
            line = bytes(self._buffer[:end]).strip(b"\n")
            del self._buffer[: end + 1]
            if self._overflow or len(line) > self._max:
                self._overflow = False
                out.append(SlcanError("line too long"))
            else:
                out.append(line)


# ---------------------------------------------------------------------------------------------- SLCAN server

OK = b"\r"
ERROR = b"\a"
VERSION_REPLY = b"V1013\r"
SERIAL_REPLY = b"NHC01\r"
MAX_PENDING_OUTPUT = 256 * 1024


@dataclass
class SlcanStats:
    lines: int = 0
    errors: int = 0
    frames_rx: int = 0
    frames_tx: int = 0
    output_dropped: int = 0
    sessions: int = 0
    internal_errors: int = 0


def _frame_line(frame_id: int, data: bytes) -> bytes:
    return f"t{frame_id:03X}{len(data)}{data.hex().upper()}\r".encode()


class SlcanServer:
    """The controller as an SLCAN adapter on a pty (``transport="pty"``) or on TCP 127.0.0.1 (``"tcp"``).

    Like a real adapter it sends nothing until the host opens the channel (``O``/``L``) and stops on ``C``;
    frames the host sends are answered ``z``. The pty slave is put in raw mode before its path is published
    and kept open by the server so the host can close and reopen it.
    """

    def __init__(
        self,
        peer: ControllerCanPeer,
        faults: CanFaultInjector | None = None,
        *,
        transport: Literal["pty", "tcp"] = "pty",
        heartbeat_period_s: float | None = None,
    ) -> None:
        self.peer = peer
        self.faults = faults or CanFaultInjector(peer.controller.config.can_faults)
        self.transport = transport
        self.heartbeat_period_s = heartbeat_period_s or peer.controller.config.heartbeat_period_s
        self.stats = SlcanStats()
        self._outbox = _Outbox(self.faults)
        self._splitter = SlcanLineSplitter()
        self._output = bytearray()
        self._open = False
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._master: int | None = None
        self._slave: int | None = None
        self._path = ""
        self._listener: socket.socket | None = None
        self._client: socket.socket | None = None
        self._wake_r, self._wake_w = -1, -1
        self._closed = False

    @property
    def channel(self) -> str:
        """The pty path (``/dev/pts/N``) or ``socket://127.0.0.1:PORT``."""
        if self.transport == "tcp" and self._listener is not None:
            return f"socket://127.0.0.1:{self._listener.getsockname()[1]}"
        return self._path

    @property
    def is_open(self) -> bool:
        """True while a host has the CAN channel open."""
        return self._open

    def start(self) -> SlcanServer:
        if self.transport == "pty":
            self._master, self._slave = os.openpty()
            tty.setraw(self._slave)
            os.set_blocking(self._master, False)
            self._path = os.ttyname(self._slave)
        else:
            self._listener = socket.create_server(("127.0.0.1", 0))
            self._listener.setblocking(False)
        self._wake_r, self._wake_w = os.pipe()
        self._thread = threading.Thread(target=self._run, name="slcan-server", daemon=True)
        self._thread.start()
        log.info("slcan_server_started", channel=self.channel)
        return self

    def close(self) -> None:
        """Stop the server thread and release the pty/socket (idempotent)."""
        if self._closed:
            return
        self._closed = True
        self._stop.set()
        if self._wake_w >= 0:
            os.write(self._wake_w, b"x")
        if self._thread is not None:
            self._thread.join(timeout=5.0)
        for fd in (self._master, self._slave, self._wake_r, self._wake_w):
            if fd is not None and fd >= 0:
                with contextlib.suppress(OSError):
                    os.close(fd)
        for sock in (self._client, self._listener):
            if sock is not None:
                sock.close()

    def __enter__(self) -> SlcanServer:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # -------------------------------------------------------------- I/O loop

    def _out_fd(self) -> int | None:
        if self.transport == "pty":
            return self._master
        return self._client.fileno() if self._client is not None else None

    def _run(self) -> None:
        """The I/O loop; an unexpected error in the controller code is logged and the loop goes on."""
        next_heartbeat = time.monotonic()
        while not self._stop.is_set():
            try:
                next_heartbeat = self._step(next_heartbeat)
            except (OSError, ValueError) as err:
                if self._stop.is_set():
                    return
                self.stats.internal_errors += 1
                log.exception("slcan_server_error", error=str(err))
                self._stop.wait(0.01)
            except Exception:
                self.stats.internal_errors += 1
                log.exception("slcan_server_error")
                self._stop.wait(0.01)

    def _step(self, next_heartbeat: float) -> float:
        """One pass: wait for input or the next deadline, handle input, heartbeat, delayed frames, output."""
        now = time.monotonic()
        deadlines = [now + 0.1]
        if self._open:
            deadlines.append(next_heartbeat)
            if self.peer.watching:
                deadlines.append(now + STATE_POLL_S)
        due = self._outbox.next_due()
        if due is not None:
            deadlines.append(due)
        timeout = max(0.0, min(deadlines) - now)
        readers = [self._wake_r]
        if self.transport == "pty":
            readers.append(self._master)
        else:
            readers.append(self._listener.fileno())
            if self._client is not None:
                readers.append(self._client.fileno())
        out_fd = self._out_fd()
        writers = [out_fd] if self._output and out_fd is not None else []
        readable, _, _ = select.select(readers, writers, [], timeout)
        if self._wake_r in readable:
            os.read(self._wake_r, 64)
        self._read_input(readable)
        now = time.monotonic()
        if self._open and now >= next_heartbeat:
            if self.faults.heartbeat:
                self._send(self._outbox.schedule(self.peer.cycle_frames(), now))
            next_heartbeat += self.heartbeat_period_s
            if next_heartbeat < now:
                next_heartbeat = now + self.heartbeat_period_s
        elif self._open and self.faults.heartbeat and self.peer.status_changed():
            self._send(self._outbox.schedule(self.peer.cycle_frames(), now))
        elif not self._open:
            next_heartbeat = now
        self._send(self._outbox.due(now) if self._open else [])
        self._flush()
        return next_heartbeat

    def _read_input(self, readable: list[int]) -> None:
        data = b""
        if self.transport == "pty":
            if self._master in readable:
                try:
                    data = os.read(self._master, 4096)
                except (BlockingIOError, InterruptedError):
                    return
                except OSError as err:
                    if err.errno != errno.EIO:
                        raise
                    return
        else:
            if self._listener.fileno() in readable:
                self._accept()
            if self._client is not None and self._client.fileno() in readable:
                try:
                    data = self._client.recv(4096)
                except (BlockingIOError, InterruptedError):
                    return
                except OSError:
                    data = b""
                if not data:
                    self._drop_client()
                    return
        for item in self._splitter.feed(data):
            self._handle_line(item)

    def _accept(self) -> None:
        try:
            client, _ = self._listener.accept()
        except (BlockingIOError, InterruptedError):
            return
        if self._client is not None:
            self._drop_client()
        client.setblocking(False)
        client.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        self._client = client

    def _drop_client(self) -> None:
        if self._client is not None:
            self._client.close()
        self._client = None
        self._close_channel()
        self._splitter = SlcanLineSplitter()

    def _close_channel(self) -> None:
        self._open = False
        self._output.clear()
        self._outbox.clear()
        if self._slave is not None:
            with contextlib.suppress(OSError):
                termios.tcflush(self._slave, termios.TCIFLUSH)

    def _reply(self, data: bytes) -> None:
        if len(self._output) + len(data) > MAX_PENDING_OUTPUT:
            self.stats.output_dropped += 1
            return
        self._output.extend(data)

    def _send(self, frames: list[Frame]) -> None:
        for frame_id, data in frames:
            self.stats.frames_tx += 1
            self._reply(_frame_line(frame_id, data))

    def _flush(self) -> None:
        fd = self._out_fd()
        if not self._output or fd is None:
            return
        try:
            written = os.write(fd, self._output)
        except (BlockingIOError, InterruptedError):
            return
        except OSError:
            self._output.clear()
            return
        del self._output[:written]

    def _handle_line(self, item: bytes | SlcanError) -> None:
        self.stats.lines += 1
        error = item if isinstance(item, SlcanError) else None
        command = None
        if error is None:
            try:
                command = parse_slcan_line(item)
            except SlcanError as err:
                error = err
        if command is None:
            self.stats.errors += 1
            log.debug("slcan_bad_line", error=str(error))
            self._reply(ERROR)
            return
        self._reply(self._execute(command))

    def _execute(self, command: SlcanCommand) -> bytes:
        code = command.code
        if code in ("O", "L"):
            if not self._open:
                self._open = True
                self.stats.sessions += 1
                self.peer.reset_session()
            return OK
        if code == "C":
            self._close_channel()
            return OK
        if code in ("S", "s"):
            return ERROR if self._open else OK
        if code in ("V", "v"):
            return VERSION_REPLY if code == "V" else b"v1013\r"
        if code == "N":
            return SERIAL_REPLY
        if code == "F":
            return b"F00\r"
        if code in ("", "Z", "X", "M", "m"):
            return OK
        if not self._open:
            return ERROR
        self.stats.frames_rx += 1
        answer = b"Z\r" if command.extended else b"z\r"
        if command.frame_id is None:
            return ERROR
        self._reply(answer)
        now = time.monotonic()
        for _, data in self.faults.apply("rx", command.frame_id, command.data):
            responses = self.peer.handle_frame(command.frame_id, data, extended=command.extended,
                                               remote=command.remote)
            self._send(self._outbox.schedule(responses, now))
        return b""


class CanBusServer:
    """Serve the controller peer on any python-can bus (``interface="virtual"`` for fast in-process tests)."""

    def __init__(
        self,
        peer: ControllerCanPeer,
        bus_config: dict[str, Any],
        faults: CanFaultInjector | None = None,
        *,
        heartbeat_period_s: float | None = None,
    ) -> None:
        self.peer = peer
        self.bus_config = dict(bus_config)
        self.faults = faults or CanFaultInjector(peer.controller.config.can_faults)
        self.heartbeat_period_s = heartbeat_period_s or peer.controller.config.heartbeat_period_s
        self._outbox = _Outbox(self.faults)
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._bus: can.BusABC | None = None

    def start(self) -> CanBusServer:
        self._bus = can.Bus(**self.bus_config)
        self._thread = threading.Thread(target=self._run, name="can-bus-server", daemon=True)
        self._thread.start()
        return self

    def close(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=5.0)
            self._thread = None
        if self._bus is not None:
            self._bus.shutdown()
            self._bus = None

    def __enter__(self) -> CanBusServer:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def _send(self, frames: list[Frame]) -> None:
        for frame_id, data in frames:
            self._bus.send(can.Message(arbitration_id=frame_id, data=data, is_extended_id=False))

    def _run(self) -> None:
        next_heartbeat = time.monotonic()
        while not self._stop.is_set():
            try:
                next_heartbeat = self._step(next_heartbeat)
            except Exception:
                log.exception("can_bus_server_error")
                self._stop.wait(0.01)

    def _step(self, next_heartbeat: float) -> float:
        now = time.monotonic()
        due = self._outbox.next_due()
        wait = min(next_heartbeat, due if due is not None else next_heartbeat) - now
        if self.peer.watching:
            wait = min(wait, STATE_POLL_S)
        msg = self._bus.recv(timeout=max(0.0, min(wait, 0.05)))
        now = time.monotonic()
        if msg is not None and not msg.is_error_frame:
            for _, data in self.faults.apply("rx", msg.arbitration_id, bytes(msg.data)):
                responses = self.peer.handle_frame(msg.arbitration_id, data, extended=msg.is_extended_id,
                                                   remote=msg.is_remote_frame)
                self._send(self._outbox.schedule(responses, now))
        if now >= next_heartbeat:
            if self.faults.heartbeat:
                self._send(self._outbox.schedule(self.peer.cycle_frames(), now))
            next_heartbeat += self.heartbeat_period_s
            if next_heartbeat < now:
                next_heartbeat = now + self.heartbeat_period_s
        elif self.faults.heartbeat and self.peer.status_changed():
            self._send(self._outbox.schedule(self.peer.cycle_frames(), now))
        self._send(self._outbox.due(now))
        return next_heartbeat
