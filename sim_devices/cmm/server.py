"""Simulated CMM speaking I++ DME 1.4.3 (``hilcal.protocols.ippdme``) on a pty and/or TCP (127.0.0.1).

``start_cmm_server`` serves one ``CmmMachine`` (``machine.py``) to every link, one ``CmmSession`` (``session.py``)
with its reader and worker threads per link (a real server listens on port 1294, 6.1; tests ask for an ephemeral
port). The server has its own command reader and formatter (it shares only the declarative protocol tables with the
driver) and never imports ``drivers``. Faults (``faults.py``) are settable at start and at run time; an emergency stop
can be pressed and released on the handle (``emergency_stop``, ``release_emergency_stop``; 6.2.4, 9.5).
"""

from __future__ import annotations

import contextlib
import errno
import os
import select
import socket
import threading
import time
import tty
from collections.abc import Mapping
from dataclasses import dataclass
from types import TracebackType
from typing import Any

import structlog

from hilcal.protocols.ippdme import MAX_LINE_CHARS, Code
from hilcal.robot import Robot
from sim_devices.cmm.config import CmmServerConfig
from sim_devices.cmm.faults import FaultInjector
from sim_devices.cmm.machine import CmmMachine
from sim_devices.cmm.session import CmmSession
from sim_devices.rig.rig import SimulatedRig

log = structlog.get_logger(__name__)


WRITE_GIVE_UP_S = 5.0
"""Output nobody reads for this long is dropped (logged), like bytes on a line with no listener."""
JOIN_TIMEOUT_S = 5.0


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
        self._machine = CmmMachine(robot, rig, config)
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
    def collisions(self) -> int:
        """Crashes of the stylus ball so far (positioning moves into a sphere, illegal touches, platform spheres that
        struck the parked ball), each logged as ``cmm_sim.collision``."""
        return self._machine.collisions

    @property
    def machine(self) -> CmmMachine:
        """The simulated machine (its position, tools and state), for tests and the launcher."""
        return self._machine

    def emergency_stop(self) -> None:
        """Press the emergency stop: the motion stops, every session gets ``E0000 ! Error(3, 0500, ...)`` and motion
        is refused (0500) until it is released and the errors are cleared."""
        log.warning("cmm_sim.emergency_stop")
        self._machine.emergency = True
        self._machine.request_stop("emergency")
        self._machine.broadcast(Code.EMERGENCY_STOP, "HealthCheck")

    def release_emergency_stop(self) -> None:
        """Release the emergency stop; the sessions stay in their error state until ClearAllErrors."""
        log.info("cmm_sim.emergency_stop_released")
        self._machine.emergency = False

    @property
    def machine_time_s(self) -> float:
        """The CMM's machine time so far (s, before ``time_scale``): travel, probing strokes, touches, homing."""
        return self._machine.machine_time_s

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

        session = CmmSession(self._machine, self.faults, send, self._stop)
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
                        if len(buf) > MAX_LINE_CHARS + 1:
                            if not discarding:  # answered once (0008), the rest up to its LF dropped
                                session.handle_line(bytes(buf[: MAX_LINE_CHARS + 1]) + b"\r")
                            discarding = True
                            buf.clear()
                        break
                    line = bytes(buf[:end])
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
            session.close()
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
        log.info("cmm_sim.stopped", path=self.path, tcp_port=self.tcp_port, collisions=self._machine.collisions,
                 machine_time_s=round(self._machine.machine_time_s, 3))

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
