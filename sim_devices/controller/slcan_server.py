"""The simulated controller as an SLCAN (Lawicel ASCII) adapter on a pseudo-terminal or a TCP socket.

``SlcanServer`` makes the ``ControllerCanPeer`` look like a USB-serial CAN adapter on a pty (or a TCP socket for
pyserial's ``socket://`` URLs), so python-can's ``slcan`` interface and the real driver code run unchanged.
"""

from __future__ import annotations

import contextlib
import errno
import os
import select
import socket
import termios
import threading
import time
import tty
from dataclasses import dataclass
from typing import Literal

import structlog

from sim_devices.controller.can_faults import CanFaultInjector, FrameOutbox
from sim_devices.controller.can_peer import STATE_POLL_S, ControllerCanPeer, Frame
from sim_devices.controller.slcan_protocol import SlcanCommand, SlcanError, SlcanLineSplitter, parse_slcan_line

log = structlog.get_logger(__name__)


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
    unplugged: int = 0


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
        self._outbox = FrameOutbox(self.faults)
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
        self._unplug = False

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

    def unplug(self) -> None:
        """Drop the host's TCP connection, as a CAN gateway that reboots or a pulled cable would (tcp only).

        The host sees its connection fail and must open the channel again; the controller runs on meanwhile.
        """
        if self.transport != "tcp":
            raise ValueError("unplug needs the tcp transport (a pty cannot be re-opened at the same path)")
        self._unplug = True
        os.write(self._wake_w, b"u")

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
        if self._unplug:
            self._unplug = False
            self.stats.unplugged += 1
            log.warning("slcan_unplugged", count=self.stats.unplugged)
            self._drop_client()
            readable = [fd for fd in readable if fd == self._wake_r]
        self._read_input(readable)
        now = time.monotonic()
        if self._open and now >= next_heartbeat:
            if self.faults.heartbeat:
                self._send(self._outbox.schedule(self.peer.cycle_frames(), now))
            next_heartbeat += self.heartbeat_period_s
            if next_heartbeat < now:
                next_heartbeat = now + self.heartbeat_period_s
        elif self._open and self.faults.heartbeat:
            self._send(self._outbox.schedule(self.peer.changed_cycle_frames(), now))
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
