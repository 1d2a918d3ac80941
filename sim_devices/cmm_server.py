"""Simulated CMM speaking the I++-DME-like line protocol of ``hilcal.protocols.cmm`` on a pty and/or TCP.

Physics: the six tooling spheres of the SimulatedRig (platform spheres moving with ``rig.true_pose()``, base
spheres fixed) expressed in the CMM frame with ``rig.to_cmm``. ``PtMeas(X,Y,Z,IJK)`` moves the probe from
target + s*IJK along -IJK for up to 2*s (s = search distance) and returns the first surface touched plus
Gaussian noise; no surface on that path is error 1006 "Surface not found". Durations are real-time
figures multiplied by ``time_scale`` (0 = instant).

This module has its own command parser and formatter (it shares only the declarative protocol tables with
the driver) and never imports ``drivers``. Faults (garbage lines, a cut line, silence, probe miss, outlier)
are drawn per command from seeded rates and one-shot injections, settable at start and at run time.
"""

from __future__ import annotations

import contextlib
import errno
import os
import re
import select
import socket
import threading
import time
import tty
from collections import Counter
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from enum import StrEnum
from types import TracebackType
from typing import Any

import numpy as np
import structlog
from pydantic import BaseModel, ConfigDict, Field
from scipy.spatial.transform import Rotation

from hilcal.protocols.cmm import (
    COORDINATE_DECIMALS,
    DEFAULT_SEARCH_DISTANCE_MM,
    ENCODING,
    ERRORS,
    LATCHING_ERRORS,
    MACHINE_VOLUME_LIMIT_MM,
    MAX_LINE_BYTES,
    MAX_SEARCH_DISTANCE_MM,
    MOTION_COMMANDS,
    NAME_PATTERN,
    NUMBER_PATTERN,
    PRINTABLE_MAX,
    PRINTABLE_MIN,
    SEARCH_PROPERTY,
    SERVER_TAG,
    SESSION_FREE_COMMANDS,
    STRING_PATTERN,
    TERMINATOR,
    Command,
    ErrorCode,
    Marker,
)
from hilcal.robot import Robot
from sim_devices.rig import SimulatedRig

log = structlog.get_logger(__name__)

WRITE_GIVE_UP_S = 5.0
"""Output nobody reads for this long is dropped (logged), like bytes on a line with no listener."""
JOIN_TIMEOUT_S = 5.0


class Fault(StrEnum):
    """Injectable faults. GARBAGE/PARTIAL/SILENCE apply to any command, MISS/OUTLIER to PtMeas only."""

    GARBAGE = "garbage"
    """Random non-protocol lines before the final response line."""
    PARTIAL = "partial"
    """The data (or final) line is cut in the middle, never finished; nothing follows."""
    SILENCE = "silence"
    """The command is dropped: no response at all, nothing executed."""
    MISS = "miss"
    """PtMeas reports "Surface not found" although the surface is there."""
    OUTLIER = "outlier"
    """PtMeas returns a point displaced outwards along the approach direction by ``outlier_mm``."""


class FaultRates(BaseModel):
    """Probability per command of each fault."""

    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)

    garbage: float = Field(default=0.0, ge=0, le=1)
    partial: float = Field(default=0.0, ge=0, le=1)
    silence: float = Field(default=0.0, ge=0, le=1)
    miss: float = Field(default=0.0, ge=0, le=1)
    outlier: float = Field(default=0.0, ge=0, le=1)


class CmmServerConfig(BaseModel):
    """The simulated CMM: noise, timing, transports and faults."""

    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)

    seed: int = 0
    noise_sigma_mm: float = Field(default=0.002, ge=0, description="touch-point noise per coordinate")
    time_scale: float = Field(default=1.0, ge=0, description="multiplies every duration; 0 = instant")
    probe_time_s: float = Field(default=0.5, ge=0, description="one touch, excluding travel")
    travel_speed_mm_s: float = Field(default=250.0, gt=0)
    home_time_s: float = Field(default=10.0, ge=0)
    pty: bool = True
    tcp_port: int | None = Field(default=None, ge=0, le=65535, description="None: no TCP; 0: ephemeral port")
    outlier_mm: float = Field(default=0.5, gt=0)
    garbage_lines: int = Field(default=2, ge=1, le=20, description="lines per GARBAGE fault")
    faults: FaultRates = FaultRates()


# ---------------------------------------------------------------------- faults


@dataclass(frozen=True)
class FaultPlan:
    """The faults applied to one command."""

    garbage: bool = False
    partial: bool = False
    silence: bool = False
    miss: bool = False
    outlier: bool = False


class FaultInjector:
    """Seeded fault rates plus one-shot injections; thread-safe, changeable while the server runs."""

    def __init__(self, rates: FaultRates, seed: int) -> None:
        self._lock = threading.Lock()
        self._rates = rates
        self._pending: Counter[tuple[Fault, str | None]] = Counter()
        self._rng = np.random.default_rng([seed, 0xFA17])
        self.applied: Counter[Fault] = Counter()
        """How often each fault has been applied so far."""

    def set_rates(self, rates: FaultRates | Mapping[str, float]) -> None:
        """Replace the per-command fault probabilities."""
        with self._lock:
            self._rates = rates if isinstance(rates, FaultRates) else FaultRates.model_validate(dict(rates))

    def inject(self, fault: Fault | str, count: int = 1, command: str | None = None) -> None:
        """Apply ``fault`` to the next ``count`` eligible commands (only commands named ``command`` if given)."""
        with self._lock:
            self._pending[(Fault(fault), command)] += count

    def pending(self) -> int:
        """One-shot injections not yet applied."""
        with self._lock:
            return sum(self._pending.values())

    def clear(self) -> None:
        """No more faults: zero rates, no pending injections."""
        with self._lock:
            self._rates = FaultRates()
            self._pending.clear()

    def draw(self, command: str) -> FaultPlan:
        """Decide the faults of the next command."""
        with self._lock:
            chosen = {}
            for fault in Fault:
                if fault in (Fault.MISS, Fault.OUTLIER) and command != Command.PT_MEAS:
                    chosen[fault] = False
                    continue
                hit = False
                for key in ((fault, command), (fault, None)):
                    if self._pending[key] > 0:
                        self._pending[key] -= 1
                        hit = True
                        break
                rate = getattr(self._rates, fault.value)
                if rate > 0 and self._rng.random() < rate:
                    hit = True
                chosen[fault] = hit
            if chosen[Fault.SILENCE]:
                chosen = {f: f is Fault.SILENCE for f in Fault}
            for fault, hit in chosen.items():
                if hit:
                    self.applied[fault] += 1
            return FaultPlan(**{f.value: hit for f, hit in chosen.items()})

    def garbage_line(self) -> bytes:
        """A random line that is not a protocol line (its first byte is never a digit)."""
        with self._lock:
            n = int(self._rng.integers(1, 60))
            body = self._rng.integers(0, 256, n).astype(np.uint8)
            first = int(self._rng.integers(0x3A, 0x100))
        body = bytes(b for b in body.tobytes() if b not in (0x0A, 0x0D))
        return bytes([first if first not in (0x0A, 0x0D) else 0x7E]) + body + TERMINATOR


# ---------------------------------------------------------------------- command parsing (server side)


@dataclass(frozen=True)
class Call:
    """``Name(arg, ...)``; args are numbers, strings or calls."""

    name: str
    args: tuple[float | str | Call, ...] = ()


@dataclass(frozen=True)
class ParsedCommand:
    tag: str
    call: Call


class CommandRejected(Exception):
    """A command line the server answers with an error (before any acknowledgement)."""

    def __init__(self, tag: str, code: ErrorCode, detail: str = "", method: str = "") -> None:
        super().__init__(f"{tag}: {code.name} {detail}")
        self.tag = tag
        self.code = code
        self.detail = detail
        self.method = method


_NAME = re.compile(NAME_PATTERN)
_NUMBER = re.compile(NUMBER_PATTERN)
_STRING = re.compile(STRING_PATTERN)
_MAX_DEPTH = 6


class _Scanner:
    """Recursive-descent reader of ``Name(arg, ...)`` over one command body."""

    def __init__(self, text: str, tag: str) -> None:
        self.text = text
        self.pos = 0
        self.tag = tag

    def fail(self, what: str) -> CommandRejected:
        return CommandRejected(self.tag, ErrorCode.PROTOCOL_ERROR, f"{what} at column {self.pos + 7}")

    def skip_spaces(self) -> None:
        while self.pos < len(self.text) and self.text[self.pos] == " ":
            self.pos += 1

    def peek(self) -> str:
        return self.text[self.pos] if self.pos < len(self.text) else ""

    def call(self, depth: int) -> Call:
        if depth > _MAX_DEPTH:
            raise self.fail("nesting too deep")
        m = _NAME.match(self.text, self.pos)
        if m is None:
            raise self.fail("expected a name")
        self.pos = m.end()
        if self.peek() != "(":
            raise self.fail("expected '('")
        self.pos += 1
        args: list[float | str | Call] = []
        self.skip_spaces()
        if self.peek() != ")":
            while True:
                self.skip_spaces()
                args.append(self.argument(depth))
                self.skip_spaces()
                if self.peek() == ",":
                    self.pos += 1
                    continue
                break
        if self.peek() != ")":
            raise self.fail("expected ')' or ','")
        self.pos += 1
        return Call(m.group(), tuple(args))

    def argument(self, depth: int) -> float | str | Call:
        for pattern in (_NUMBER, _STRING):
            m = pattern.match(self.text, self.pos)
            if m is not None:
                self.pos = m.end()
                if pattern is _STRING:
                    return m.group()[1:-1]
                value = float(m.group())
                if not np.isfinite(value):
                    raise CommandRejected(self.tag, ErrorCode.ARGUMENT_OUT_OF_RANGE, "number too large")
                return value
        return self.call(depth + 1)


def parse_command_line(raw: bytes) -> ParsedCommand:
    """Parse one command line (terminator removed); raises CommandRejected, nothing else."""
    if len(raw) > MAX_LINE_BYTES:
        raise CommandRejected(SERVER_TAG, ErrorCode.PROTOCOL_ERROR, "line too long")
    head = raw[:5]
    if len(head) < 5 or not head.isdigit() or head == SERVER_TAG.encode():
        raise CommandRejected(SERVER_TAG, ErrorCode.ILLEGAL_TAG)
    tag = head.decode(ENCODING)
    if raw[5:6] != b" ":
        raise CommandRejected(tag, ErrorCode.NO_SPACE_AT_POS_6)
    if any(not PRINTABLE_MIN <= b <= PRINTABLE_MAX for b in raw):
        raise CommandRejected(tag, ErrorCode.ILLEGAL_CHARACTER)
    scanner = _Scanner(raw[6:].decode(ENCODING), tag)
    call = scanner.call(0)
    scanner.skip_spaces()
    if scanner.pos != len(scanner.text):
        raise scanner.fail("unexpected text after the command")
    return ParsedCommand(tag, call)


def _axes(call: Call, allowed: tuple[str, ...], required: tuple[str, ...]) -> dict[str, tuple[float, ...]]:
    """``X(x), Y(y), IJK(i, j, k)`` style arguments by name; each argument a call of numbers, names unique."""
    out: dict[str, tuple[float, ...]] = {}
    for arg in call.args:
        if not isinstance(arg, Call) or arg.name not in allowed or arg.name in out:
            raise ValueError(f"unexpected argument {arg!r}")
        if not arg.args or not all(isinstance(a, float) for a in arg.args):
            raise ValueError(f"{arg.name} needs numbers")
        out[arg.name] = tuple(float(a) for a in arg.args)  # type: ignore[arg-type]
    missing = [name for name in required if name not in out]
    if missing:
        raise ValueError(f"missing {', '.join(missing)}")
    for name, values in out.items():
        if len(values) != (3 if name == "IJK" else 1):
            raise ValueError(f"{name} has {len(values)} values")
    return out


# ---------------------------------------------------------------------- machine and session


class _Abort(Exception):
    """A motion that failed after its acknowledgement."""

    def __init__(self, code: ErrorCode, detail: str = "") -> None:
        super().__init__(code.name)
        self.code = code
        self.detail = detail


class _Machine:
    """Axes, homing, error state and the touch physics; shared by all connections."""

    def __init__(self, robot: Robot, rig: SimulatedRig, config: CmmServerConfig) -> None:
        self.robot = robot
        self.rig = rig
        self.config = config
        self.lock = threading.Lock()
        self.homed = False
        self.position_mm = np.zeros(3)
        self.latched: ErrorCode | None = None
        self._rng = np.random.default_rng([config.seed, 0xC33])

    def sphere_centres_mm(self) -> np.ndarray:
        """(6, 3) true sphere centres in the CMM frame: platform spheres first, then base spheres."""
        pose = self.rig.true_pose()
        rot = Rotation.from_euler("ZYX", pose[[5, 4, 3]], degrees=True)
        platform_base = rot.apply(self.robot.platform_spheres) + pose[:3]
        return self.rig.to_cmm(np.vstack([platform_base, self.robot.base_spheres]))

    def _travel_s(self, to_mm: np.ndarray) -> float:
        return float(np.linalg.norm(to_mm - self.position_mm)) / self.config.travel_speed_mm_s

    def home(self) -> float:
        self.homed = True
        self.position_mm = np.zeros(3)
        return self.config.home_time_s

    def goto(self, target: np.ndarray) -> float:
        r = self.robot.sphere_radius_mm
        if np.any(np.linalg.norm(self.sphere_centres_mm() - target, axis=1) < r):
            raise _Abort(ErrorCode.COLLISION, "GoTo target inside a sphere")
        duration = self._travel_s(target)
        self.position_mm = target
        return duration

    def touch(self, target: np.ndarray, ijk: np.ndarray, search_mm: float, plan: FaultPlan) -> tuple[np.ndarray, float]:
        """The touched point (noisy) and the duration; _Abort on a miss or a start inside a sphere."""
        norm = float(np.linalg.norm(ijk))
        if norm == 0:
            raise _Abort(ErrorCode.VECTOR_HAS_NO_NORM)
        n = ijk / norm
        start = target + search_mm * n
        duration = self._travel_s(start) + self.config.probe_time_s
        self.position_mm = start
        centres = self.sphere_centres_mm()
        r = self.robot.sphere_radius_mm
        m = start - centres
        if np.any(np.linalg.norm(m, axis=1) < r):
            raise _Abort(ErrorCode.ILLEGAL_TOUCH, "probe start inside a sphere")
        b = m @ -n
        c = np.sum(m * m, axis=1) - r * r
        disc = b * b - c
        with np.errstate(invalid="ignore"):
            s = np.where(disc >= 0, -b - np.sqrt(np.maximum(disc, 0.0)), np.inf)
        s = np.where((s >= 0) & (s <= 2.0 * search_mm), s, np.inf)
        if plan.miss or not np.isfinite(s.min()):
            raise _Abort(ErrorCode.SURFACE_NOT_FOUND, "injected miss" if plan.miss else "")
        point = start - s.min() * n + self._rng.normal(0.0, self.config.noise_sigma_mm, 3)
        if plan.outlier:
            point = point + self.config.outlier_mm * n
        return point, duration


def _fmt(value: float) -> str:
    return f"{value:.{COORDINATE_DECIMALS}f}"


def _error_body(code: ErrorCode, method: str, detail: str) -> str:
    spec = ERRORS[code]
    text = spec.text + (f": {detail}" if detail else "")
    safe = "".join(ch if PRINTABLE_MIN <= ord(ch) <= PRINTABLE_MAX and ch != '"' else "'" for ch in text)
    safe_method = "".join(ch for ch in method if ch.isalnum() or ch == ".")
    return f'{Marker.ERROR} Error({int(spec.severity)}, {int(code):04d}, "{safe_method}", "{safe}")'


class _Session:
    """One connection's protocol state; turns command lines into response bytes through ``send``."""

    def __init__(
        self,
        machine: _Machine,
        faults: FaultInjector,
        send: Callable[[bytes], None],
        wait: Callable[[float], bool],
    ) -> None:
        self.machine = machine
        self.faults = faults
        self.send = send
        self.wait = wait  # sleeps for a duration; True if the server is stopping
        self.in_session = False
        self.search_mm = DEFAULT_SEARCH_DISTANCE_MM

    def handle_line(self, raw: bytes) -> None:
        """Answer one command line (terminator removed)."""
        try:
            cmd = parse_command_line(raw)
        except CommandRejected as rej:
            log.info("cmm_sim.rejected", code=int(rej.code), detail=rej.detail, raw=raw[:200])
            self._emit(rej.tag, [], _error_body(rej.code, rej.method, rej.detail), FaultPlan())
            return
        try:
            action = self._check(cmd.call)
        except CommandRejected as rej:
            log.info("cmm_sim.rejected", tag=cmd.tag, code=int(rej.code), detail=rej.detail)
            self._emit(cmd.tag, [], _error_body(rej.code, cmd.call.name, rej.detail), FaultPlan())
            return
        plan = self.faults.draw(cmd.call.name)
        if plan.silence:
            log.info("cmm_sim.fault_silence", tag=cmd.tag, command=cmd.call.name)
            return
        self._send_line(f"{cmd.tag} {Marker.ACK}")
        data: list[str] = []
        try:
            with self.machine.lock:
                duration, data = action(plan)
        except _Abort as abort:
            with self.machine.lock:
                if abort.code in LATCHING_ERRORS:
                    self.machine.latched = abort.code
            if self.wait(self.machine.config.probe_time_s * self.machine.config.time_scale):
                return
            self._emit(cmd.tag, [], _error_body(abort.code, cmd.call.name, abort.detail), plan)
            return
        if self.wait(duration * self.machine.config.time_scale):
            return
        self._emit(cmd.tag, data, str(Marker.DONE), plan)

    def _send_line(self, text: str) -> None:
        self.send(text.encode(ENCODING) + TERMINATOR)

    def _emit(self, tag: str, data: list[str], final: str, plan: FaultPlan) -> None:
        """Data lines then the final line, with the planned garbage and cut applied."""
        lines = [f"{tag} {Marker.DATA} {d}" for d in data] + [f"{tag} {final}"]
        if plan.partial:
            cut = lines[0].encode(ENCODING)
            log.info("cmm_sim.fault_partial", tag=tag, sent=cut[: len(cut) // 2])
            self.send(cut[: len(cut) // 2])
            return
        for i, line in enumerate(lines):
            if plan.garbage and i == len(lines) - 1:
                for _ in range(self.machine.config.garbage_lines):
                    self.send(self.faults.garbage_line())
            self._send_line(line)

    def _check(self, call: Call) -> Callable[[FaultPlan], tuple[float, list[str]]]:
        """Validate a command in the current state; the action to run after the acknowledgement."""
        try:
            name = Command(call.name)
        except ValueError:
            raise CommandRejected("", ErrorCode.UNSUPPORTED_COMMAND, call.name[:40]) from None
        if not self.in_session and name not in SESSION_FREE_COMMANDS:
            raise CommandRejected("", ErrorCode.BAD_CONTEXT, "no session (StartSession first)")
        m = self.machine
        try:
            if name in (Command.START_SESSION, Command.END_SESSION, Command.HOME, Command.CLEAR_ALL_ERRORS):
                if call.args:
                    raise ValueError(f"{name} takes no arguments")
            if name in MOTION_COMMANDS:
                with m.lock:
                    latched, homed = m.latched, m.homed
                if latched is not None:
                    raise CommandRejected("", ErrorCode.TRANSACTION_ABORTED, f"after error {int(latched):04d}")
                if name is not Command.HOME and not homed:
                    raise CommandRejected("", ErrorCode.BAD_CONTEXT, "machine not homed (Home first)")
            match name:
                case Command.START_SESSION:
                    return self._start_session
                case Command.END_SESSION:
                    return self._end_session
                case Command.HOME:
                    return lambda _plan: (m.home(), [])
                case Command.CLEAR_ALL_ERRORS:
                    return self._clear
                case Command.GET_ERROR_INFO:
                    return self._error_info(call)
                case Command.SET_PROP:
                    return self._set_prop(call)
                case Command.GO_TO:
                    axes = _axes(call, ("X", "Y", "Z"), ())
                    if not axes:
                        raise ValueError("GoTo needs at least one of X, Y, Z")
                    target = self._target(axes)
                    return lambda _plan: (m.goto(target), [])
                case Command.PT_MEAS:
                    axes = _axes(call, ("X", "Y", "Z", "IJK"), ("X", "Y", "Z", "IJK"))
                    target = self._target(axes)
                    ijk = np.array(axes["IJK"])
                    search = self.search_mm

                    def ptmeas(plan: FaultPlan) -> tuple[float, list[str]]:
                        point, duration = m.touch(target, ijk, search, plan)
                        return duration, [f"X({_fmt(point[0])}), Y({_fmt(point[1])}), Z({_fmt(point[2])})"]

                    return ptmeas
        except ValueError as err:
            raise CommandRejected("", ErrorCode.INCORRECT_ARGUMENTS, str(err)[:80]) from None
        raise CommandRejected("", ErrorCode.UNSUPPORTED_COMMAND, call.name)

    def _target(self, axes: dict[str, tuple[float, ...]]) -> np.ndarray:
        with self.machine.lock:
            target = self.machine.position_mm.copy()
        for i, axis in enumerate(("X", "Y", "Z")):
            if axis in axes:
                target[i] = axes[axis][0]
        if np.any(np.abs(target) > MACHINE_VOLUME_LIMIT_MM):
            raise CommandRejected("", ErrorCode.OUT_OF_MACHINE_VOLUME)
        return target

    def _start_session(self, _plan: FaultPlan) -> tuple[float, list[str]]:
        self.in_session = True
        self.search_mm = DEFAULT_SEARCH_DISTANCE_MM
        self.machine.latched = None
        return 0.0, []

    def _end_session(self, _plan: FaultPlan) -> tuple[float, list[str]]:
        self.in_session = False
        return 0.0, []

    def _clear(self, _plan: FaultPlan) -> tuple[float, list[str]]:
        self.machine.latched = None
        return 0.0, []

    def _error_info(self, call: Call) -> Callable[[FaultPlan], tuple[float, list[str]]]:
        if len(call.args) != 1 or not isinstance(call.args[0], float) or call.args[0] != int(call.args[0]):
            raise ValueError("GetErrorInfo needs one integer code")
        try:
            code = ErrorCode(int(call.args[0]))
        except ValueError:
            raise CommandRejected("", ErrorCode.ARGUMENT_OUT_OF_RANGE, "unknown error code") from None
        return lambda _plan: (0.0, [f'ErrorInfo({int(code):04d}, "{ERRORS[code].text}")'])

    def _set_prop(self, call: Call) -> Callable[[FaultPlan], tuple[float, list[str]]]:
        if len(call.args) != 1 or not isinstance(call.args[0], Call):
            raise ValueError("SetProp needs one property")
        prop = call.args[0]
        if prop.name != SEARCH_PROPERTY:
            raise CommandRejected("", ErrorCode.BAD_PROPERTY, prop.name[:60])
        if len(prop.args) != 1 or not isinstance(prop.args[0], float):
            raise ValueError(f"{SEARCH_PROPERTY} needs one number")
        value = prop.args[0]
        if not 0 < value <= MAX_SEARCH_DISTANCE_MM:
            raise CommandRejected(
                "", ErrorCode.ARGUMENT_OUT_OF_RANGE, f"search distance must be in (0, {MAX_SEARCH_DISTANCE_MM}]"
            )

        def apply(_plan: FaultPlan) -> tuple[float, list[str]]:
            self.search_mm = value
            return 0.0, []

        return apply


# ---------------------------------------------------------------------- transports


class _Stopped(Exception):
    pass


@dataclass
class _Link:
    """One byte stream served by one thread."""

    fd: int
    name: str
    owned: bool
    """Close the fd when the link ends (TCP connections), not for the pty master."""
    thread: threading.Thread | None = None
    sock: socket.socket | None = None


class CmmServerHandle:
    """A running simulated CMM. ``path``: pty slave to open as a serial port; ``tcp_port`` or None."""

    def __init__(self, robot: Robot, rig: SimulatedRig, config: CmmServerConfig) -> None:
        self.config = config
        self.faults = FaultInjector(config.faults, config.seed)
        self._machine = _Machine(robot, rig, config)
        self._stop = threading.Event()
        self._wake_r, self._wake_w = os.pipe()
        self._links: list[_Link] = []
        self._links_lock = threading.Lock()
        self._threads: list[threading.Thread] = []
        self._master: int | None = None
        self._slave: int | None = None
        self._listener: socket.socket | None = None
        self.path: str | None = None
        self.tcp_port: int | None = None
        self.commands_handled = 0
        try:
            if config.pty:
                self._open_pty()
            if config.tcp_port is not None:
                self._open_tcp(config.tcp_port)
        except BaseException:
            self.close()
            raise
        log.info("cmm_sim.started", path=self.path, tcp_port=self.tcp_port)

    @property
    def socket_url(self) -> str | None:
        """pyserial URL of the TCP endpoint."""
        return None if self.tcp_port is None else f"socket://127.0.0.1:{self.tcp_port}"

    def _open_pty(self) -> None:
        master, slave = os.openpty()
        self._master, self._slave = master, slave
        tty.setraw(slave)
        os.set_blocking(master, False)
        link = _Link(master, "pty", owned=False)
        self._start_link(link)
        self.path = os.ttyname(slave)

    def _open_tcp(self, port: int) -> None:
        self._listener = socket.create_server(("127.0.0.1", port))
        self._listener.setblocking(False)
        self.tcp_port = self._listener.getsockname()[1]
        t = threading.Thread(target=self._accept_loop, name="cmm-sim-accept", daemon=True)
        self._threads.append(t)
        t.start()

    def _accept_loop(self) -> None:
        assert self._listener is not None
        while not self._stop.is_set():
            ready, _, _ = select.select([self._listener, self._wake_r], [], [])
            if self._wake_r in ready or self._stop.is_set():
                return
            try:
                conn, peer = self._listener.accept()
            except (BlockingIOError, InterruptedError):
                continue
            except OSError:
                return
            conn.setblocking(False)
            conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            log.info("cmm_sim.tcp_connected", peer=peer)
            self._start_link(_Link(conn.fileno(), f"tcp {peer[0]}:{peer[1]}", owned=True, sock=conn))

    def _start_link(self, link: _Link) -> None:
        link.thread = threading.Thread(target=self._serve, args=(link,), name=f"cmm-sim {link.name}", daemon=True)
        with self._links_lock:
            self._links.append(link)
        link.thread.start()

    def _write_all(self, fd: int, data: bytes) -> None:
        view = memoryview(data)
        give_up = time.monotonic() + WRITE_GIVE_UP_S
        while view:
            if self._stop.is_set():
                raise _Stopped
            try:
                n = os.write(fd, view)
                view = view[n:]
                continue
            except BlockingIOError:
                pass
            if time.monotonic() > give_up:
                log.warning("cmm_sim.output_dropped", n_bytes=len(view))
                return
            select.select([self._wake_r], [fd], [], 0.1)

    def _serve(self, link: _Link) -> None:
        """Read command lines from one stream and answer them until stopped or the peer goes away."""

        def send(data: bytes) -> None:
            self._write_all(link.fd, data)

        session = _Session(self._machine, self.faults, send, self._stop.wait)
        buf = bytearray()
        discarding = False
        try:
            while not self._stop.is_set():
                ready, _, _ = select.select([link.fd, self._wake_r], [], [])
                if self._wake_r in ready:
                    return
                try:
                    chunk = os.read(link.fd, 4096)
                except (BlockingIOError, InterruptedError):
                    continue
                except OSError as err:
                    if err.errno == errno.EIO:
                        time.sleep(0.01)
                        continue
                    log.info("cmm_sim.link_closed", link=link.name, error=str(err))
                    return
                if not chunk:
                    log.info("cmm_sim.link_closed", link=link.name)
                    return
                buf += chunk
                while True:
                    end = buf.find(b"\n")
                    if end < 0:
                        if len(buf) > MAX_LINE_BYTES + len(TERMINATOR):
                            if not discarding:
                                session.handle_line(bytes(buf))
                            discarding = True
                            buf.clear()
                        break
                    line = bytes(buf[:end]).removesuffix(b"\r")
                    del buf[: end + 1]
                    if discarding:
                        discarding = False
                        continue
                    self.commands_handled += 1
                    session.handle_line(line)
        except _Stopped:
            return
        except Exception:
            log.exception("cmm_sim.link_failed", link=link.name)
        finally:
            if link.owned and link.sock is not None:
                with contextlib.suppress(OSError):
                    link.sock.close()

    def close(self) -> None:
        """Stop every thread and close every descriptor; idempotent."""
        if self._stop.is_set():
            return
        self._stop.set()
        with contextlib.suppress(OSError):
            os.write(self._wake_w, b"x")
        with self._links_lock:
            links = list(self._links)
        for t in [*self._threads, *(link.thread for link in links if link.thread is not None)]:
            t.join(JOIN_TIMEOUT_S)
            if t.is_alive():
                log.warning("cmm_sim.thread_did_not_stop", thread=t.name)
        for link in links:
            if link.sock is not None:
                with contextlib.suppress(OSError):
                    link.sock.close()
        if self._listener is not None:
            self._listener.close()
        for fd in (self._master, self._slave, self._wake_r, self._wake_w):
            if fd is not None:
                with contextlib.suppress(OSError):
                    os.close(fd)
        log.info("cmm_sim.stopped", path=self.path, tcp_port=self.tcp_port)

    def __enter__(self) -> CmmServerHandle:
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.close()


def start_cmm_server(
    robot: Robot, rig: SimulatedRig, config: CmmServerConfig | Mapping[str, Any] | None = None
) -> CmmServerHandle:
    """Start the simulated CMM for the rig; returns a handle with ``.path``, ``.tcp_port``, ``.faults``, ``.close()``.

    Do not move the rig while a measurement is in progress: the server reads ``rig.true_pose()`` per touch.
    """
    if config is None:
        cfg = CmmServerConfig()
    elif isinstance(config, CmmServerConfig):
        cfg = config
    else:
        cfg = CmmServerConfig.model_validate(dict(config))
    return CmmServerHandle(robot, rig, cfg)
