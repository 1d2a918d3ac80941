"""I++ DME 1.4.3 server for a simulated Cartesian CMM, written as an independent test peer.

The server speaks the application-port protocol of the I++ DME specification 1.4.3 over TCP:

* one accept thread per server, and per connection a reader thread (parses lines, sends the
  Ack ``&`` at once, runs event commands on the fast queue) and a worker thread (runs the
  normal FIFO queue), sections 4, 6.2.3 and 6.2.4;
* responses ``&`` / ``#`` / ``!`` / ``%`` in the order required by section 6.2.3, ``%`` also
  after an error;
* error state handling of sections 6.2.5, 6.3.1.5 and 8.1 (severity >= 2 needs
  ClearAllErrors);
* a simulated machine whose probe is a ball moving among spherical artefacts.

Usage::

    server = IppDmeServer(lambda: [((0.0, 0.0, 0.0), 12.5)])
    ... connect a client to server.url ...
    server.close()
"""

from __future__ import annotations

import contextlib
import math
import queue
import socket
import threading
import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass

import numpy as np

from .machine import (
    CSY_CHAIN,
    TRANSFORM_NAMES,
    CoordinateSystems,
    CsyTransform,
    Limits,
    Param,
    Sphere,
    ToolModel,
    exit_fraction,
    first_contact,
    inside_limits,
    make_tools,
)
from .protocol import (
    ERRORS,
    MAX_LINE,
    Command,
    IppError,
    LineError,
    NumArg,
    PropArg,
    StrArg,
    TagArg,
    WordArg,
    check_characters,
    fmt_number,
    parse_method,
    parse_tag,
)

SphereSpec = tuple[tuple[float, float, float], float]

DME_VERSION = "1.4.3"
#: Commands of the fast queue end with "E" and need an EventTag (section 6.2.1).
EVENT_COMMANDS = frozenset({"AbortE", "GetErrStatusE", "GetPropE", "OnMoveReportE"})
#: Commands accepted in the error state (6.2.5), plus EndSession (6.3.1) and AbortE.
ALLOWED_IN_ERROR = frozenset({"ClearAllErrors", "GetErrStatusE", "GetXtdErrStatus",
                              "EndSession", "AbortE"})
#: Moving commands; an error ends their implicit DisableUser() (6.3.2.12).
MOTION_COMMANDS = frozenset({"Home", "GoTo", "PtMeas"})
AXES = ("X", "Y", "Z")
TOOL_AXES = ("Tool.A", "Tool.B", "Tool.C")
#: Allowed OnPtMeasReport items: Get() items plus IJK(), ER(), Q() (6.3.2.6).
PTMEAS_REPORT_ITEMS = AXES + TOOL_AXES + ("IJK", "ER", "Q")
#: Default report format set by StartSession (6.3.1.1).
DEFAULT_PTMEAS_REPORT = ("X", "Y", "Z")
#: Position items an OnMoveReportE daemon can report (6.3.2.7).
MOVE_REPORT_ITEMS = AXES + TOOL_AXES
#: At most 10 OnMoveReportE responses per second (6.3.2.7).
MIN_REPORT_INTERVAL = 0.1
DEFAULT_LIMITS: Limits = ((-2000.0, 2000.0), (-2000.0, 2000.0), (-2000.0, 2000.0))


@dataclass
class _Job:
    """An entry of a connection's normal (FIFO) queue.

    ``kind`` is ``"command"`` for a normal transaction, ``"done"`` for the Transaction
    complete of an event transaction (sent "in the order of the standard queue", 6.2.4) and
    ``"abort_done"`` for the Transaction complete of AbortE (6.3.1.5).
    """

    seq: int
    tag: str
    kind: str
    command: Command | None = None
    error: IppError | None = None


@dataclass
class _Daemon:
    """An OnMoveReportE daemon (sections 4.3, 6.3.2.7)."""

    tag: str
    items: tuple[str, ...]
    period: float | None
    distance: float | None
    last_pos: np.ndarray
    last_time: float = -math.inf


class _Connection:
    """One TCP client: socket, queues and the session state bound to it."""

    def __init__(self, sock: socket.socket, number: int) -> None:
        self.sock = sock
        self.number = number
        self.send_lock = threading.Lock()
        self.jobs: queue.Queue[_Job | None] = queue.Queue()
        self.closed = False
        self.session = False
        self.errors: list[IppError] = []
        self.seq = 0
        self.error_epoch = 0
        self.abort_epoch = 0
        self.abort = threading.Event()
        self.daemons: dict[str, _Daemon] = {}
        self.ptmeas_report: tuple[str, ...] = DEFAULT_PTMEAS_REPORT
        self.threads: list[threading.Thread] = []


class _Context:
    """Per-transaction helper handed to command handlers."""

    def __init__(self, server: IppDmeServer, conn: _Connection, tag: str, name: str) -> None:
        self.server = server
        self.conn = conn
        self.tag = tag
        self.name = name
        self.completion = "done"

    def data(self, text: str) -> None:
        """Send a Data response ``tag # text``."""
        self.server._send(self.conn, f"{self.tag} # {text}")

    def error_line(self, error: IppError) -> None:
        """Send an Error response without changing the error state (status reports)."""
        self.server._send(self.conn, f"{self.tag} ! {error.payload()}")


# --------------------------------------------------------------------------- argument helpers

def _no_args(cmd: Command) -> None:
    if cmd.args:
        raise IppError(502, cmd.name, "method takes no arguments")


def _one_string(cmd: Command) -> str:
    if len(cmd.args) != 1:
        raise IppError(502, cmd.name, "method takes exactly one argument")
    arg = cmd.args[0]
    if not isinstance(arg, StrArg):
        raise IppError(509, cmd.name, "argument must be a string")
    return arg.value


def _properties(cmd: Command) -> list[PropArg]:
    """Argument list that is an enumeration of properties (section 6.1.3: no duplicates)."""
    if not cmd.args:
        raise IppError(502, cmd.name, "the enumeration must not be empty")
    seen: set[str] = set()
    props: list[PropArg] = []
    for arg in cmd.args:
        if not isinstance(arg, PropArg):
            raise IppError(502, cmd.name, f"{arg} is not a property")
        if arg.name in seen:
            raise IppError(502, cmd.name, f"{arg.name} appears twice in the enumeration")
        seen.add(arg.name)
        props.append(arg)
    return props


def _one_value(prop: PropArg, method: str) -> float:
    if len(prop.values) != 1:
        raise IppError(502, method, f"{prop.name}() needs exactly one number")
    return prop.values[0]


def _no_values(prop: PropArg, method: str) -> None:
    if prop.values:
        raise IppError(502, method, f"{prop.name}() takes no numbers here")


def _vector(values: Iterable[float]) -> str:
    return ", ".join(fmt_number(float(v)) for v in values)


# --------------------------------------------------------------------------- server

class IppDmeServer:
    """I++ DME 1.4.3 server (application port, section 2.4.1) for a simulated CartCMM.

    ``spheres`` is called whenever geometry is needed (at each moving command) and returns the
    current artefacts as ``[((x, y, z), radius), ...]`` in machine coordinates (mm).

    Keyword options beyond the required ones:

    * ``time_scale``: 0 = instant motion; otherwise motion takes
      ``distance / speed * time_scale`` seconds (speeds from GoToPar / PtMeasPar).
    * ``limits``: axis travel ((xmin, xmax), (ymin, ymax), (zmin, zmax)) in machine coordinates.
    * ``home_xyz`` / ``homed``: home position and whether the machine starts homed.
    * ``probe_name``: name of the measuring probe (AvrRadius = ``stylus_radius_mm``).
    * ``initial_tool``: active tool at power-up (state "left over", 6.3.1.1).
    * ``ijk_report``: what IJK() reports after PtMeas, ``"probe_direction"`` (the normalised
      probing direction, like a touch-trigger probe) or ``"surface_normal"`` (the true
      normal of the touched sphere).

    Public attributes: ``port``, ``url``, ``commands`` (number of command lines that opened a
    transaction) and ``transcript`` (list of ``(direction, line)`` with direction
    ``"client"``, ``"server"`` or ``"note"`` for error details).
    """

    def __init__(self, spheres: Callable[[], list[SphereSpec]], host: str = "127.0.0.1",
                 port: int = 0, stylus_radius_mm: float = 1.5, noise_mm: float = 0.0005,
                 seed: int = 0, *, time_scale: float = 0.0, limits: Limits = DEFAULT_LIMITS,
                 home_xyz: tuple[float, float, float] = (0.0, 0.0, 0.0), homed: bool = False,
                 probe_name: str = "Probe1", initial_tool: str = "NoTool",
                 ijk_report: str = "probe_direction") -> None:
        if ijk_report not in ("probe_direction", "surface_normal"):
            raise ValueError("ijk_report must be 'probe_direction' or 'surface_normal'")
        self._spheres = spheres
        self._noise = float(noise_mm)
        self._rng = np.random.default_rng(seed)
        self._time_scale = float(time_scale)
        self._limits = limits
        self._home = np.array(home_xyz, dtype=float)
        self._ijk_report = ijk_report
        self._tools: dict[str, ToolModel] = make_tools(probe_name, float(stylus_radius_mm))
        if initial_tool not in self._tools:
            raise ValueError(f"unknown initial tool {initial_tool!r}")
        self._active = self._tools[initial_tool]
        self._found = self._tools["UnDefTool"]
        self._csy = CoordinateSystems()
        self._pos = self._home.copy()
        self._homed = homed
        self._user_enabled = False
        self._owner: _Connection | None = None

        self.commands = 0
        self.transcript: list[tuple[str, str]] = []
        self._lock = threading.RLock()
        self._transcript_lock = threading.Lock()
        self._connections: list[_Connection] = []
        self._stopping = threading.Event()
        self._handlers: dict[str, Callable[[_Context, Command], None]] = {
            name[len("_cmd_"):]: getattr(self, name)
            for name in dir(self) if name.startswith("_cmd_")
        }

        self._listener = socket.create_server((host, port))
        self._listener.settimeout(0.1)
        self.host = host
        self.port: int = self._listener.getsockname()[1]
        self.url = f"socket://{host}:{self.port}"
        self._accept_thread = threading.Thread(target=self._accept_loop, daemon=True,
                                               name=f"ippdme-accept-{self.port}")
        self._accept_thread.start()

    # ------------------------------------------------------------------ public helpers

    @property
    def position_mm(self) -> tuple[float, float, float]:
        """Current ball centre in machine coordinates."""
        with self._lock:
            return tuple(float(v) for v in self._pos)

    @property
    def active_tool(self) -> str:
        """Name of the active tool."""
        with self._lock:
            return self._active.name

    def close(self) -> None:
        """Stop accepting, disconnect all clients and join every thread."""
        self._stopping.set()
        self._listener.close()
        self._accept_thread.join(timeout=5)
        with self._lock:
            connections = list(self._connections)
        for conn in connections:
            with contextlib.suppress(OSError):
                conn.sock.shutdown(socket.SHUT_RDWR)
        for conn in connections:
            for thread in conn.threads:
                thread.join(timeout=5)

    def __enter__(self) -> IppDmeServer:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # ------------------------------------------------------------------ TCP layer

    def _accept_loop(self) -> None:
        """Accept clients (section 9.2); each gets a reader and a worker thread."""
        number = 0
        while not self._stopping.is_set():
            try:
                sock, _ = self._listener.accept()
            except TimeoutError:
                continue
            except OSError:
                break
            number += 1
            sock.settimeout(None)
            sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            conn = _Connection(sock, number)
            conn.threads = [
                threading.Thread(target=self._read_loop, args=(conn,), daemon=True,
                                 name=f"ippdme-read-{self.port}-{number}"),
                threading.Thread(target=self._work_loop, args=(conn,), daemon=True,
                                 name=f"ippdme-work-{self.port}-{number}"),
            ]
            with self._lock:
                self._connections.append(conn)
            for thread in conn.threads:
                thread.start()

    def _read_loop(self, conn: _Connection) -> None:
        """Split the byte stream into CommandLines terminated by <CR><LF> (6.1.1, 6.2)."""
        buffer = b""
        try:
            while not self._stopping.is_set():
                chunk = conn.sock.recv(65536)
                if not chunk:
                    break
                buffer += chunk
                while (end := buffer.find(b"\n")) >= 0:
                    raw, buffer = buffer[:end], buffer[end + 1:]
                    self._handle_line(conn, raw)
                if len(buffer) > MAX_LINE + 2:
                    buffer = b""
                    self._send(conn, f"E0000 ! {IppError(0, 'Parser').payload()}")
        except OSError:
            pass
        finally:
            self._disconnect(conn)

    def _disconnect(self, conn: _Connection) -> None:
        """Closing the connection ends its session implicitly (9.3)."""
        with self._lock:
            conn.closed = True
            if conn.session:
                self._end_session(conn)
            if conn in self._connections:
                self._connections.remove(conn)
        conn.abort.set()
        conn.jobs.put(None)
        with contextlib.suppress(OSError):
            conn.sock.close()

    def _send(self, conn: _Connection, line: str) -> None:
        """Send one ResponseLine followed by <CR><LF>."""
        with conn.send_lock:
            if conn.closed:
                return
            with self._transcript_lock:
                self.transcript.append(("server", line))
            try:
                conn.sock.sendall(line.encode("ascii") + b"\r\n")
            except OSError:
                conn.closed = True

    def _note(self, text: str) -> None:
        with self._transcript_lock:
            self.transcript.append(("note", text))

    # ------------------------------------------------------------------ line handling

    def _handle_line(self, conn: _Connection, raw: bytes) -> None:
        """Tag check, Ack, then fast queue (event tag) or normal queue (6.2.1, 6.2.3, 4.1).

        A line whose tag is illegal gets only ``E0000 ! Error(..)`` (6.2.1); every other line
        is acknowledged and completed with ``%`` even if it is wrong.
        """
        text = raw.decode("latin-1")
        terminated = text.endswith("\r")
        if terminated:
            text = text[:-1]
        with self._transcript_lock:
            self.transcript.append(("client", text))
        bad_characters = not terminated or not check_characters(text)
        try:
            tag = parse_tag(text)
        except LineError as exc:
            error = IppError(7, "Parser", "illegal character or lone CR/LF") \
                if bad_characters else exc.error
            self._note(f"E0000: {error}")
            self._send(conn, f"E0000 ! {error.payload()}")
            self._enter_error_state(conn, error)
            return
        with self._lock:
            self.commands += 1
        self._send(conn, f"{tag} &")
        command: Command | None = None
        error: IppError | None = None
        if bad_characters:
            error = IppError(7, "Parser", "illegal character or lone CR/LF (6.1.1)")
        else:
            try:
                command = parse_method(tag, text)
            except IppError as exc:
                error = exc
        if tag.startswith("E"):
            self._run_event(conn, tag, command, error)
        else:
            self._enqueue(conn, "command", tag, command, error)

    def _enqueue(self, conn: _Connection, kind: str, tag: str,
                 command: Command | None = None, error: IppError | None = None) -> None:
        with self._lock:
            conn.seq += 1
            conn.jobs.put(_Job(conn.seq, tag, kind, command, error))

    def _run_event(self, conn: _Connection, tag: str, command: Command | None,
                   error: IppError | None) -> None:
        """Fast queue: execute now, queue the Transaction complete behind the normal queue."""
        ctx = _Context(self, conn, tag, command.name if command else "Parser")
        try:
            if error is not None:
                raise error
            assert command is not None
            self._execute(ctx, command)
        except IppError as exc:
            self._report(ctx, exc)
        except Exception as exc:
            self._report(ctx, IppError(511, ctx.name, repr(exc)))
        self._enqueue(conn, ctx.completion, tag)

    def _work_loop(self, conn: _Connection) -> None:
        while (job := conn.jobs.get()) is not None:
            if not conn.closed:
                self._run_job(conn, job)

    def _run_job(self, conn: _Connection, job: _Job) -> None:
        """Run one normal-queue entry; every transaction ends with ``%`` (6.2.3.1)."""
        if job.kind == "abort_done":
            conn.abort.clear()
        if job.kind != "command":
            self._send(conn, f"{job.tag} %")
            return
        name = job.command.name if job.command else "Parser"
        ctx = _Context(self, conn, job.tag, name)
        with self._lock:
            pending = job.seq <= max(conn.error_epoch, conn.abort_epoch)
        try:
            if pending:
                raise IppError(6, name, "pending transaction aborted (6.2.5, 6.3.1.5)",
                               record=False)
            if job.error is not None:
                raise job.error
            assert job.command is not None
            self._execute(ctx, job.command)
        except IppError as exc:
            self._report(ctx, exc)
        except Exception as exc:
            self._report(ctx, IppError(511, name, repr(exc)))
        self._send(conn, f"{job.tag} %")

    def _report(self, ctx: _Context, error: IppError) -> None:
        """Send the error line(s); severity >= 2 puts the session into error state (8.1)."""
        for item in (*error.preceding, error):
            ctx.error_line(item)
        if error.detail:
            self._note(f"{ctx.tag} {error.code:04d} {ctx.name}: {error.detail}")
        if error.record and error.severity >= 2:
            self._enter_error_state(ctx.conn, error)
            if ctx.name in MOTION_COMMANDS:
                with self._lock:
                    self._user_enabled = True

    def _enter_error_state(self, conn: _Connection, error: IppError) -> None:
        """Store the error; on entering the error state all pending transactions abort (6.2.5)."""
        if error.severity < 2:
            return
        with self._lock:
            if not conn.errors:
                conn.error_epoch = conn.seq
            conn.errors.append(error)

    def _execute(self, ctx: _Context, cmd: Command) -> None:
        """Session, tag-type and error-state checks, then the command handler.

        * unknown method: 0501 (as an older server answers GetDMEVersion, 6.3.1.14);
        * event command without event tag or vice versa: 0001 (6.2.1);
        * no session: only StartSession and EndSession are accepted, else 0008 (6.3.1);
        * error state: only the commands of 6.2.5 run, others get 0511 + 0514 (6.3.1.7
          example).
        """
        handler = self._handlers.get(cmd.name)
        if handler is None:
            raise IppError(501, cmd.name, "command not implemented by this server")
        if (cmd.name in EVENT_COMMANDS) != cmd.is_event:
            raise IppError(1, cmd.name, "fast-queue commands need an event tag and only they")
        with self._lock:
            in_session = ctx.conn.session
            in_error = bool(ctx.conn.errors)
        if not in_session and cmd.name not in ("StartSession", "EndSession"):
            raise IppError(8, cmd.name, "no session active")
        if in_session and cmd.name == "StartSession":
            raise IppError(8, cmd.name, "session already active")
        if in_session and in_error and cmd.name not in ALLOWED_IN_ERROR:
            raise IppError(514, cmd.name, "server is in error state", record=False,
                           preceding=(IppError(511, cmd.name, severity=2, record=False),))
        handler(ctx, cmd)

    # ------------------------------------------------------------------ machine helpers

    def _world(self) -> list[Sphere]:
        return [Sphere(np.asarray(centre, dtype=float), float(radius))
                for centre, radius in self._spheres()]

    def _csy_position(self) -> np.ndarray:
        with self._lock:
            return self._csy.point_from_machine(self._pos.copy())

    def _item_value(self, item: str) -> float:
        """Value of X()/Y()/Z() (selected csy, 6.3.3.5-7) or Tool.A()/B()/C() (6.3.8)."""
        if item in AXES:
            return float(self._csy_position()[AXES.index(item)])
        return 0.0

    def _items_text(self, items: Iterable[str]) -> str:
        return ", ".join(f"{item}({fmt_number(self._item_value(item))})" for item in items)

    def _require_homed(self, method: str) -> None:
        """Section 6.3.2.1: the machine must be homed before moving commands."""
        if not self._homed:
            raise IppError(507, method, "machine is not homed (6.3.2.1)")

    def _require_tool(self, method: str) -> ToolModel:
        with self._lock:
            tool = self._active
        if not tool.defined:
            raise IppError(1503, method, "active tool is UnDefTool")
        return tool

    def _speed(self, block: str) -> float:
        with self._lock:
            params = self._active.block(block) or self._tools["BaseTool"].block(block)
            assert params is not None
            return params["Speed"].actual

    def _move(self, ctx: _Context, target: np.ndarray, speed: float) -> None:
        """Straight move of the ball centre; timed if ``time_scale`` > 0; honours AbortE."""
        with self._lock:
            start = self._pos.copy()
        distance = float(np.linalg.norm(target - start))
        if ctx.conn.abort.is_set():
            raise IppError(6, ctx.name, "aborted by AbortE")
        if self._time_scale > 0.0 and distance > 0.0:
            duration = distance / max(speed, 1e-6) * self._time_scale
            began = time.monotonic()
            while True:
                fraction = min(1.0, (time.monotonic() - began) / duration)
                with self._lock:
                    self._pos = start + fraction * (target - start)
                self._daemon_tick(ctx.conn)
                if ctx.conn.abort.is_set():
                    raise IppError(6, ctx.name, "aborted by AbortE while moving")
                if fraction >= 1.0:
                    break
                time.sleep(min(0.02, duration * (1.0 - fraction)))
        else:
            with self._lock:
                self._pos = target.copy()
        self._daemon_tick(ctx.conn)

    def _move_checked(self, ctx: _Context, target: np.ndarray, speed: float,
                      spheres: list[Sphere], radius: float) -> None:
        """Move, stopping at the first contact with an artefact (error 2504 Collision)."""
        with self._lock:
            start = self._pos.copy()
        hit = first_contact(start, target, spheres, radius)
        if hit is not None:
            self._move(ctx, start + hit[0] * (target - start), speed)
            raise IppError(2504, ctx.name, "probe ball would enter an artefact")
        self._move(ctx, target, speed)

    def _daemon_tick(self, conn: _Connection, force: bool = False) -> None:
        """Fire OnMoveReportE daemons whose Time/Dis condition holds (6.3.2.7)."""
        now = time.monotonic()
        with self._lock:
            position = self._pos.copy()
            due: list[_Daemon] = []
            for daemon in conn.daemons.values():
                moved = float(np.linalg.norm(position - daemon.last_pos))
                if not force:
                    if moved == 0.0 or now - daemon.last_time < MIN_REPORT_INTERVAL:
                        continue
                    by_distance = daemon.distance is not None and moved >= daemon.distance
                    by_time = daemon.period is not None and now - daemon.last_time >= daemon.period
                    unconditional = daemon.distance is None and daemon.period is None
                    if not (by_distance or by_time or unconditional):
                        continue
                daemon.last_pos, daemon.last_time = position, now
                due.append(daemon)
            lines = [f"{daemon.tag} # {self._items_text(daemon.items)}" for daemon in due]
        for line in lines:
            self._send(conn, line)

    def _end_session(self, conn: _Connection) -> None:
        """Stop all daemons and release the session (6.3.1.2); machine state is kept."""
        with self._lock:
            conn.daemons.clear()
            conn.session = False
            if self._owner is conn:
                self._owner = None

    # ------------------------------------------------------------------ server methods (6.3.1)

    def _cmd_StartSession(self, ctx: _Context, cmd: Command) -> None:
        """6.3.1.1: one session at a time (0008 otherwise); clears errors, resets reports."""
        _no_args(cmd)
        with self._lock:
            if self._owner is not None and self._owner is not ctx.conn:
                raise IppError(8, cmd.name, "another client holds the session")
            self._owner = ctx.conn
            conn = ctx.conn
            conn.session = True
            conn.errors.clear()
            conn.daemons.clear()
            conn.ptmeas_report = DEFAULT_PTMEAS_REPORT

    def _cmd_EndSession(self, ctx: _Context, cmd: Command) -> None:
        """6.3.1.2: ends the session; does nothing if none is active."""
        _no_args(cmd)
        if ctx.conn.session:
            self._end_session(ctx.conn)

    def _cmd_StopDaemon(self, ctx: _Context, cmd: Command) -> None:
        """6.3.1.3: StopDaemon(EventTag); 0513 if there is no such daemon."""
        if len(cmd.args) != 1:
            raise IppError(502, cmd.name, "needs exactly one event tag")
        arg = cmd.args[0]
        if not isinstance(arg, TagArg):
            raise IppError(509, cmd.name, "argument must be an event tag")
        with self._lock:
            if ctx.conn.daemons.pop(arg.tag, None) is None:
                raise IppError(513, cmd.name, f"no daemon {arg.tag}")

    def _cmd_StopAllDaemons(self, ctx: _Context, cmd: Command) -> None:
        """6.3.1.4: stop all daemons; warning 0512 if none is active."""
        _no_args(cmd)
        with self._lock:
            had_daemons = bool(ctx.conn.daemons)
            ctx.conn.daemons.clear()
        if not had_daemons:
            raise IppError(512, cmd.name)

    def _cmd_AbortE(self, ctx: _Context, cmd: Command) -> None:
        """6.3.1.5: abort the running and all pending transactions; then ClearAllErrors.

        The running command stops (timed motion) with 0006, pending ones get 0006, and the
        AbortE Transaction complete is queued behind them.  Daemons keep running.
        """
        _no_args(cmd)
        conn = ctx.conn
        with self._lock:
            conn.abort_epoch = conn.seq
            conn.abort.set()
        self._enter_error_state(conn, IppError(6, cmd.name, "AbortE"))
        ctx.completion = "abort_done"

    def _cmd_GetErrorInfo(self, ctx: _Context, cmd: Command) -> None:
        """6.3.1.6: GetErrorInfo(ErrorNumber) -> the text of section 8.2 as a String."""
        if len(cmd.args) != 1:
            raise IppError(502, cmd.name, "needs exactly one error number")
        arg = cmd.args[0]
        if not isinstance(arg, NumArg) or arg.value != int(arg.value) or not 0 <= arg.value <= 9999:
            raise IppError(509, cmd.name, "argument must be an error number 0..9999")
        text = ERRORS.get(int(arg.value), (0, "Unknown error number"))[1]
        ctx.data(f'"{text}"')

    def _cmd_ClearAllErrors(self, ctx: _Context, cmd: Command) -> None:
        """6.3.1.7: leave the error state."""
        _no_args(cmd)
        with self._lock:
            ctx.conn.errors.clear()

    def _cmd_GetProp(self, ctx: _Context, cmd: Command) -> None:
        """6.3.1.9: GetProp(Tool.PtMeasPar.Speed(), ...) -> one line with all values."""
        props = _properties(cmd)
        for prop in props:
            _no_values(prop, cmd.name)
        with self._lock:
            ctx.data(", ".join(self._get_property(prop.name, cmd.name) for prop in props))

    def _cmd_GetPropE(self, ctx: _Context, cmd: Command) -> None:
        """6.3.1.10: GetProp on the fast queue."""
        self._cmd_GetProp(ctx, cmd)

    def _cmd_SetProp(self, ctx: _Context, cmd: Command) -> None:
        """6.3.1.11, 6.3.6, 6.3.7: set Act values; out of range -> clamp + warning 0504."""
        props = _properties(cmd)
        updates: list[tuple[Param, float]] = []
        with self._lock:
            for prop in props:
                head, *rest = prop.name.split(".")
                tool = self._resolve_tool(head, cmd.name)
                if not tool.defined:
                    raise IppError(1503, cmd.name, "tool is UnDefTool")
                if tool.name == "BaseTool":
                    raise IppError(509, cmd.name, "BaseTool is not an instance for usage")
                if rest and rest[0] in ("Name", "Id", "AvrRadius", "Alignment",
                                        "CollisionVolume", "AlignmentVolume"):
                    raise IppError(509, cmd.name, f"{prop.name} cannot be set")
                param, sub = self._param(tool, rest, cmd.name)
                if sub != "Act":
                    raise IppError(509, cmd.name, "only Act values can be set (6.3.7)")
                updates.append((param, _one_value(prop, cmd.name)))
            clamped = [param.set_actual(value) for param, value in updates]
        if any(clamped):
            self._report(ctx, IppError(504, cmd.name, "value clamped to [Min, Max]"))

    def _cmd_EnumProp(self, ctx: _Context, cmd: Command) -> None:
        """6.3.1.12 / 7.7: names and types of the direct children."""
        self._enumerate(ctx, cmd, recursive=False)

    def _cmd_EnumAllProp(self, ctx: _Context, cmd: Command) -> None:
        """6.3.1.13 / 7.8: names and types of children and all grandchildren."""
        self._enumerate(ctx, cmd, recursive=True)

    def _cmd_GetDMEVersion(self, ctx: _Context, cmd: Command) -> None:
        """6.3.1.14: DMEVersion("1.4.3")."""
        _no_args(cmd)
        ctx.data(f'DMEVersion("{DME_VERSION}")')

    # ------------------------------------------------------------------ DME methods (6.3.2)

    def _cmd_Home(self, ctx: _Context, cmd: Command) -> None:
        """6.3.2.1: move to the fixed home position; 1005 if it is occupied by an artefact."""
        _no_args(cmd)
        with self._lock:
            radius = self._active.radius
            self._user_enabled = False
        reach = [float(np.linalg.norm(self._home - s.centre)) - s.radius - radius
                 for s in self._world()]
        if reach and min(reach) < 0.0:
            raise IppError(1005, cmd.name, "home position is inside an artefact")
        self._move(ctx, self._home.copy(), self._speed("GoToPar"))
        with self._lock:
            self._homed = True

    def _cmd_IsHomed(self, ctx: _Context, cmd: Command) -> None:
        """6.3.2.2: IsHomed(0|1)."""
        _no_args(cmd)
        ctx.data(f"IsHomed({int(self._homed)})")

    def _cmd_EnableUser(self, ctx: _Context, cmd: Command) -> None:
        """6.3.2.3."""
        _no_args(cmd)
        with self._lock:
            self._user_enabled = True

    def _cmd_DisableUser(self, ctx: _Context, cmd: Command) -> None:
        """6.3.2.4."""
        _no_args(cmd)
        with self._lock:
            self._user_enabled = False

    def _cmd_IsUserEnabled(self, ctx: _Context, cmd: Command) -> None:
        """6.3.2.5: IsUserEnabled(0|1)."""
        _no_args(cmd)
        ctx.data(f"IsUserEnabled({int(self._user_enabled)})")

    def _cmd_OnPtMeasReport(self, ctx: _Context, cmd: Command) -> None:
        """6.3.2.6: format (sequence) of PtMeas results; unknown items -> 0510."""
        props = _properties(cmd)
        for prop in props:
            _no_values(prop, cmd.name)
            if prop.name not in PTMEAS_REPORT_ITEMS:
                raise IppError(510, cmd.name, f"{prop.name}() cannot be reported")
        with self._lock:
            ctx.conn.ptmeas_report = tuple(prop.name for prop in props)

    def _cmd_OnMoveReportE(self, ctx: _Context, cmd: Command) -> None:
        """6.3.2.7: start the (single) move report daemon; 0515 if one exists."""
        period: float | None = None
        distance: float | None = None
        items: list[str] = []
        for prop in _properties(cmd):
            if prop.name == "Time":
                period = _one_value(prop, cmd.name)
            elif prop.name == "Dis":
                distance = _one_value(prop, cmd.name)
            elif prop.name in MOVE_REPORT_ITEMS:
                _no_values(prop, cmd.name)
                items.append(prop.name)
            else:
                raise IppError(510, cmd.name, f"{prop.name}() cannot be reported")
        if not items:
            raise IppError(502, cmd.name, "nothing to report")
        warn = False
        if period is not None and period < 0.1:
            period, warn = 0.1, True
        if distance is not None and distance < 0.0:
            distance, warn = 0.0, True
        with self._lock:
            if ctx.conn.daemons:
                raise IppError(515, cmd.name, "stop the running OnMoveReportE daemon first")
            ctx.conn.daemons[ctx.tag] = _Daemon(ctx.tag, tuple(items), period, distance,
                                                self._pos.copy())
        if warn:
            self._report(ctx, IppError(504, cmd.name, "Time >= 0.1 s and Dis >= 0 required"))

    def _cmd_GetMachineClass(self, ctx: _Context, cmd: Command) -> None:
        """6.3.2.8: GetMachineClass(CartCMM) (an enumeration, not a string since 1.4.1)."""
        _no_args(cmd)
        ctx.data("GetMachineClass(CartCMM)")

    def _cmd_GetErrStatusE(self, ctx: _Context, cmd: Command) -> None:
        """6.3.2.9: ErrStatus(1) while in error state."""
        _no_args(cmd)
        ctx.data(f"ErrStatus({int(bool(ctx.conn.errors))})")

    def _cmd_GetXtdErrStatus(self, ctx: _Context, cmd: Command) -> None:
        """6.3.2.10: status lines, then the stored errors and 0512 if no daemon runs."""
        _no_args(cmd)
        with self._lock:
            errors = list(ctx.conn.errors)
            daemons = bool(ctx.conn.daemons)
        ctx.data(f"IsHomed({int(self._homed)})")
        ctx.data(f"IsUserEnabled({int(self._user_enabled)})")
        for error in errors:
            ctx.error_line(error)
        if not daemons:
            ctx.error_line(IppError(512, cmd.name))

    def _cmd_Get(self, ctx: _Context, cmd: Command) -> None:
        """6.3.2.11: Get(X(), Y(), Z(), Tool.A(), ...) in the requested order (6.2.2.2)."""
        props = _properties(cmd)
        for prop in props:
            _no_values(prop, cmd.name)
            if prop.name == "R":
                raise IppError(509, cmd.name, "CartCMM has no rotary table")
            if prop.name == "IJK":
                raise IppError(508, cmd.name, "IJK() only in OnPtMeasReport/OnScanReport")
            if prop.name in ("ER", "Q"):
                raise IppError(509, cmd.name, f"{prop.name}() only in OnReport methods")
            if prop.name not in MOVE_REPORT_ITEMS:
                raise IppError(510, cmd.name, f"{prop.name}() is not a readable item")
        self._require_tool(cmd.name)
        with self._lock:
            ctx.data(self._items_text(prop.name for prop in props))

    def _cmd_GoTo(self, ctx: _Context, cmd: Command) -> None:
        """6.3.2.12: straight multi-axis move; 2500 outside limits, 2504 on collision.

        Axes not given keep their value; Tool.A/B/C of the fixed probes can only be 0 (2505).
        """
        target = self._csy_position()
        for prop in _properties(cmd):
            if prop.name in AXES:
                target[AXES.index(prop.name)] = _one_value(prop, cmd.name)
            elif prop.name in TOOL_AXES:
                if abs(_one_value(prop, cmd.name)) > 1e-9:
                    raise IppError(2505, cmd.name, "the probe has no rotational axes")
            elif prop.name == "R":
                raise IppError(509, cmd.name, "CartCMM has no rotary table")
            elif prop.name == "IJK":
                raise IppError(508, cmd.name, "IJK(..) is not a GoTo argument")
            else:
                raise IppError(510, cmd.name, f"{prop.name}() is not a GoTo axis")
        self._require_homed(cmd.name)
        tool = self._require_tool(cmd.name)
        with self._lock:
            target_m = self._csy.point_to_machine(target)
        if not inside_limits(target_m, self._limits):
            raise IppError(2500, cmd.name, "target outside the machine limits")
        with self._lock:
            self._user_enabled = False
        self._move_checked(ctx, target_m, self._speed("GoToPar"), self._world(), tool.radius)

    def _cmd_PtMeas(self, ctx: _Context, cmd: Command) -> None:
        """6.3.2.13: single point measurement.

        Nominal X,Y,Z is the nominal surface point (axes not given keep their current value).
        IJK is normalised; without IJK it is the direction from the nominal point to the
        current position.  Components of IJK along axes that were not given are dropped so
        those axes do not move (6.3.2.13, "its value ... must be the same").  The ball centre
        goes to the approach position nominal + IJK * (Approach + radius), searches towards
        nominal - IJK * Search, latches the ball centre at the first contact (reported per
        OnPtMeasReport, with Gaussian noise), then retracts to contact + IJK * Retract, or back
        to the approach position if Retract < 0.
        """
        current = self._csy_position()
        nominal = current.copy()
        given = np.zeros(3, dtype=bool)
        ijk: np.ndarray | None = None
        for prop in _properties(cmd):
            if prop.name in AXES:
                index = AXES.index(prop.name)
                nominal[index] = _one_value(prop, cmd.name)
                given[index] = True
            elif prop.name == "IJK":
                if len(prop.values) != 3:
                    raise IppError(502, cmd.name, "IJK() needs three numbers")
                ijk = np.array(prop.values, dtype=float)
            elif prop.name == "R":
                raise IppError(509, cmd.name, "CartCMM has no rotary table")
            elif prop.name in TOOL_AXES:
                raise IppError(502, cmd.name, f"{prop.name}() is not a PtMeas argument")
            else:
                raise IppError(510, cmd.name, f"{prop.name}() is not a PtMeas argument")
        if not given.any():
            raise IppError(502, cmd.name, "IJK() without X(), Y() or Z() is not allowed")
        self._require_homed(cmd.name)
        tool = self._require_tool(cmd.name)
        if not tool.can_measure or tool.ptmeas_par is None:
            raise IppError(2002, cmd.name, f"{tool.name} cannot measure")
        direction = ijk * given if ijk is not None else current - nominal
        norm = float(np.linalg.norm(direction))
        if norm < 1e-12:
            raise IppError(1010, cmd.name, "probing direction has no norm")
        direction_csy = direction / norm
        with self._lock:
            nominal_m = self._csy.point_to_machine(nominal)
            normal = self._csy.vector_to_machine(direction_csy)
            approach = tool.ptmeas_par["Approach"].actual
            search = tool.ptmeas_par["Search"].actual
            retract = tool.ptmeas_par["Retract"].actual
        approach_point = nominal_m + normal * (approach + tool.radius)
        search_end = nominal_m - normal * search
        if not inside_limits(approach_point, self._limits):
            raise IppError(2500, cmd.name, "approach position outside the machine limits")
        with self._lock:
            self._user_enabled = False
        spheres = self._world()
        goto_speed = self._speed("GoToPar")
        self._move_checked(ctx, approach_point, goto_speed, spheres, tool.radius)

        limit_fraction = exit_fraction(approach_point, search_end, self._limits)
        hit = first_contact(approach_point, search_end, spheres, tool.radius)
        if hit is None or hit[0] > limit_fraction:
            stop = approach_point + limit_fraction * (search_end - approach_point)
            self._move(ctx, stop, self._speed("PtMeasPar"))
            if limit_fraction < 1.0:
                raise IppError(2500, cmd.name, "search left the machine limits")
            raise IppError(1006, cmd.name, "no contact within the search distance")
        contact = approach_point + hit[0] * (search_end - approach_point)
        self._move(ctx, contact, self._speed("PtMeasPar"))
        latched = contact + self._rng.normal(0.0, self._noise, 3)
        surface_normal = contact - hit[1].centre
        surface_normal /= np.linalg.norm(surface_normal)

        retract_point = contact + normal * retract if retract >= 0.0 else approach_point
        self._move_checked(ctx, retract_point, goto_speed, spheres, tool.radius)

        with self._lock:
            point = self._csy.point_from_machine(latched)
            if self._ijk_report == "surface_normal":
                reported_ijk = self._csy.vector_from_machine(surface_normal)
            else:
                reported_ijk = direction_csy
            fields = []
            for item in ctx.conn.ptmeas_report:
                if item in AXES:
                    value = fmt_number(float(point[AXES.index(item)]))
                elif item == "IJK":
                    value = _vector(reported_ijk)
                elif item == "ER":
                    value = fmt_number(tool.radius)
                else:
                    value = fmt_number(0.0)
                fields.append(f"{item}({value})")
        ctx.data(", ".join(fields))

    # ------------------------------------------------------------------ tool handling

    def _cmd_FindTool(self, ctx: _Context, cmd: Command) -> None:
        """6.3.2.16: FoundTool := named tool, or UnDefTool with error 1502."""
        name = _one_string(cmd)
        with self._lock:
            tool = self._tools.get(name)
            if tool is None or not tool.defined:
                self._found = self._tools["UnDefTool"]
                raise IppError(1502, cmd.name, f"no tool {name!r}")
            self._found = tool

    def _changeable_tool(self, name: str, method: str) -> ToolModel:
        tool = self._tools.get(name)
        if tool is None or not tool.changeable:
            raise IppError(1502, method, f"{name!r} is not a tool that can be activated")
        return tool

    def _activate(self, tool: ToolModel) -> None:
        """A new active tool starts with Act = Def (6.3.6, 6.3.7)."""
        if tool is not self._active:
            self._active = tool
            tool.reset_actuals()

    def _cmd_ChangeTool(self, ctx: _Context, cmd: Command) -> None:
        """6.3.2.18: activate a tool (BaseTool/UnDefTool generate 1502, 6.3.2.14)."""
        name = _one_string(cmd)
        with self._lock:
            tool = self._changeable_tool(name, cmd.name)
            self._user_enabled = False
            self._activate(tool)
        self._daemon_tick(ctx.conn, force=True)

    def _cmd_SetTool(self, ctx: _Context, cmd: Command) -> None:
        """6.3.2.19: assume the named tool is active (no motion)."""
        name = _one_string(cmd)
        with self._lock:
            self._activate(self._changeable_tool(name, cmd.name))
        self._daemon_tick(ctx.conn, force=True)

    def _cmd_GetChangeToolAction(self, ctx: _Context, cmd: Command) -> None:
        """6.3.2.26: all tools sit on one head with equal offsets: Switch, X(0), Y(0), Z(0)."""
        self._changeable_tool(_one_string(cmd), cmd.name)
        zero = fmt_number(0.0)
        ctx.data(f"ChangeToolAction(Switch, X({zero}), Y({zero}), Z({zero}))")

    def _cmd_EnumTools(self, ctx: _Context, cmd: Command) -> None:
        """6.3.2.23: one String per line; BaseTool and UnDefTool are not visible (6.3.2.14)."""
        _no_args(cmd)
        for tool in self._tools.values():
            if tool.enumerable:
                ctx.data(f'"{tool.name}"')

    # ------------------------------------------------------------------ CartCMM methods (6.3.3)

    def _cmd_SetCoordSystem(self, ctx: _Context, cmd: Command) -> None:
        """6.3.3.1: select MachineCsy, MoveableMachineCsy, MultipleArmCsy or PartCsy."""
        if len(cmd.args) != 1:
            raise IppError(502, cmd.name, "needs exactly one coordinate system")
        arg = cmd.args[0]
        if not isinstance(arg, WordArg) or arg.word not in CSY_CHAIN:
            raise IppError(509, cmd.name, "unknown coordinate system (enums are unquoted)")
        with self._lock:
            self._csy.active = arg.word
        self._daemon_tick(ctx.conn, force=True)

    def _cmd_GetCoordSystem(self, ctx: _Context, cmd: Command) -> None:
        """6.3.3.2: CoordSystem(Arg)."""
        _no_args(cmd)
        ctx.data(f"CoordSystem({self._csy.active})")

    def _transform_name(self, cmd: Command) -> str:
        arg = cmd.args[0]
        if not isinstance(arg, WordArg) or arg.word not in TRANSFORM_NAMES:
            raise IppError(509, cmd.name, "unknown transformation enumerator")
        return arg.word

    def _cmd_GetCsyTransformation(self, ctx: _Context, cmd: Command) -> None:
        """6.3.3.3: GetCsyTransformation(X0, Y0, Z0, Theta, Psi, Phi)."""
        if len(cmd.args) != 1:
            raise IppError(502, cmd.name, "needs exactly one enumerator")
        with self._lock:
            transform = self._csy.transforms[self._transform_name(cmd)]
            ctx.data(f"GetCsyTransformation({_vector(transform.origin + transform.angles)})")

    def _cmd_SetCsyTransformation(self, ctx: _Context, cmd: Command) -> None:
        """6.3.3.4: Theta must lie in 0..180 (1007); Psi and Phi are taken modulo 360."""
        if len(cmd.args) != 7:
            raise IppError(502, cmd.name, "needs an enumerator and six numbers")
        name = self._transform_name(cmd)
        numbers = cmd.args[1:]
        if not all(isinstance(arg, NumArg) for arg in numbers):
            raise IppError(509, cmd.name, "X0, Y0, Z0, Theta, Psi, Phi must be numbers")
        x0, y0, z0, theta, psi, phi = (arg.value for arg in numbers)  # type: ignore[union-attr]
        if not 0.0 <= theta <= 180.0:
            raise IppError(1007, cmd.name, f"theta {theta} not in 0..180")
        with self._lock:
            self._csy.transforms[name] = CsyTransform((x0, y0, z0),
                                                      (theta, psi % 360.0, phi % 360.0))
            moved = name in CSY_CHAIN[1:CSY_CHAIN.index(self._csy.active) + 1]
        if moved:
            self._daemon_tick(ctx.conn, force=True)

    # ------------------------------------------------------------------ properties

    def _resolve_tool(self, head: str, method: str) -> ToolModel:
        """``Tool`` is the active tool (6.3.2.15), ``FoundTool`` the FindTool result (6.3.2.17)."""
        if head == "Tool":
            return self._active
        if head == "FoundTool":
            return self._found
        raise IppError(510, method, f"{head} is neither Tool nor FoundTool")

    def _param(self, tool: ToolModel, rest: list[str], method: str) -> tuple[Param, str]:
        """Resolve ``GoToPar|PtMeasPar . Param [. Max|Min|Act|Def]`` (6.3.6, 6.3.7)."""
        if len(rest) not in (2, 3):
            raise IppError(510, method, f"unknown property {'.'.join(rest)}")
        block = tool.block(rest[0])
        param = block.get(rest[1]) if block else None
        sub = rest[2] if len(rest) == 3 else "Act"
        if param is None or sub not in ("Max", "Min", "Act", "Def"):
            raise IppError(510, method, f"{tool.name} has no property {'.'.join(rest)}")
        return param, sub

    def _get_property(self, path: str, method: str) -> str:
        """``path(value)`` for one GetProp argument (6.3.1.9, 6.3.10 - 6.3.14)."""
        head, *rest = path.split(".")
        tool = self._resolve_tool(head, method)
        if rest == ["Name"]:
            return f'{path}("{tool.name}")'
        if not tool.defined:
            raise IppError(1503, method, "tool is UnDefTool")
        if rest == ["Id"]:
            return f'{path}("{tool.name}")'
        if rest == ["AvrRadius"]:
            return f"{path}({fmt_number(tool.radius)})"
        if rest and rest[0] in ("Alignment", "CollisionVolume", "AlignmentVolume"):
            if head != "Tool" or len(rest) != 1:
                raise IppError(508, method, f"only GetProp(Tool.{rest[0]}())")
            return f"{path}({self._geometry_property(rest[0], tool)})"
        param, sub = self._param(tool, rest, method)
        return f"{path}({fmt_number(param.value(sub))})"

    def _geometry_property(self, name: str, tool: ToolModel) -> str:
        """Alignment (6.3.12), CollisionVolume (6.3.11), AlignmentVolume (6.3.14)."""
        csy = self._csy
        if name == "Alignment":
            return _vector(csy.vector_from_machine(np.array([0.0, 0.0, 1.0])))
        if name == "AlignmentVolume":
            return f"SPH, {_vector((0.0, 0.0, 0.0, tool.radius))}"
        axes = [csy.vector_from_machine(axis) for axis in np.eye(3)]
        values = [0.0, 0.0, 0.0, tool.radius, tool.radius, tool.radius]
        return f"OBB, {_vector(values + [float(v) for axis in axes for v in axis])}"

    def _children(self, tool: ToolModel, rest: list[str], method: str) -> list[tuple[str, str]]:
        """Direct children of a property node with their types (7.7)."""
        if not rest:
            entries = [("Name", "String"), ("Id", "String"), ("AvrRadius", "Number")]
            return entries + [(block, "Property") for block in ("GoToPar", "PtMeasPar")
                              if tool.block(block) is not None]
        if len(rest) == 1 and tool.block(rest[0]) is not None:
            names = list(tool.block(rest[0]) or {})
            return [(n, "Number") for n in names] + [(n, "Property") for n in names]
        if len(rest) == 2:
            self._param(tool, rest, method)
            return [(sub, "Number") for sub in ("Max", "Min", "Act", "Def")]
        raise IppError(510, method, f"{tool.name} has no property {'.'.join(rest)}")

    def _enumerate(self, ctx: _Context, cmd: Command, recursive: bool) -> None:
        if len(cmd.args) != 1 or not isinstance(cmd.args[0], PropArg) or cmd.args[0].values:
            raise IppError(502, cmd.name, "needs one property pointer like Tool.PtMeasPar()")
        head, *rest = cmd.args[0].name.split(".")
        with self._lock:
            tool = self._resolve_tool(head, cmd.name)
            if not tool.defined:
                raise IppError(1503, cmd.name, "tool is UnDefTool")
            entries = self._descendants(tool, rest, cmd.name, recursive)
        for name, kind in entries:
            ctx.data(f'"{name}", "{kind}"')

    def _descendants(self, tool: ToolModel, rest: list[str], method: str,
                     recursive: bool, prefix: str = "") -> list[tuple[str, str]]:
        children = self._children(tool, rest, method)
        entries = [(prefix + name, kind) for name, kind in children]
        if recursive:
            for name, kind in children:
                if kind == "Property":
                    entries += self._descendants(tool, [*rest, name], method, True,
                                                 f"{prefix}{name}.")
        return entries
