"""The simulated controller's Modbus parameter interface on real transports: Modbus TCP and Modbus RTU on a pty, at
the addresses of a register map (``register_map``; default hilcal's own ``hilcal-1.1``).

Small servers of our own around ``ModbusProtocol`` (see ``modbus_frames.py`` for why not pymodbus' server).
"""

from __future__ import annotations

import contextlib
import os
import select
import socket
import threading
import time

import structlog

from hilcal.protocols.modbus_map import RegisterMap
from sim_devices.controller.modbus_faults import ModbusFaultInjector
from sim_devices.controller.modbus_frames import (
    MBAP_BYTES,
    ModbusFrameError,
    parse_mbap,
    rtu_frame,
    rtu_request_length,
    rtu_split,
)
from sim_devices.controller.modbus_protocol import ControllerRegisterMap, ExecutedWrite, ModbusProtocol
from sim_devices.controller.state_machine import SimulatedController

log = structlog.get_logger(__name__)


RTU_GAP_S = 0.005
"""Silence that ends a frame whose length the function code does not tell (no real baud timing on a pty)."""


class ModbusTcpServer:
    """Modbus TCP on 127.0.0.1 (port 0 = ephemeral; see ``port``), one thread per connection."""

    def __init__(
        self,
        controller: SimulatedController,
        *,
        host: str = "127.0.0.1",
        port: int = 0,
        device_id: int | None = None,
        faults: ModbusFaultInjector | None = None,
        register_map: RegisterMap | None = None,
    ) -> None:
        self.controller = controller
        self.faults = faults or ModbusFaultInjector(controller.config.modbus_faults)
        self.protocol = ModbusProtocol(
            ControllerRegisterMap(controller, register_map), device_id or controller.config.device_id, self.faults
        )
        self._address = (host, port)
        self._port = port
        self._listener: socket.socket | None = None
        self._stop = threading.Event()
        self._threads: list[threading.Thread] = []
        self._connections: set[socket.socket] = set()
        self._conn_lock = threading.Lock()
        self.connections_accepted = 0

    @property
    def port(self) -> int:
        """The bound TCP port (an ephemeral one when constructed with port 0)."""
        if self._listener is None:
            raise RuntimeError("server not started")
        return self._port

    @property
    def writes(self) -> list[ExecutedWrite]:
        """Every write request that was executed, in order."""
        return self.protocol.writes

    def start(self) -> ModbusTcpServer:
        self._listener = socket.create_server(self._address)
        self._listener.settimeout(0.1)
        self._port = self._listener.getsockname()[1]
        thread = threading.Thread(target=self._accept_loop, name="modbus-accept", daemon=True)
        thread.start()
        self._threads.append(thread)
        log.info("modbus_server_started", port=self.port)
        return self

    def disconnect_clients(self) -> None:
        """Close every open client connection now."""
        with self._conn_lock:
            for conn in list(self._connections):
                with contextlib.suppress(OSError):
                    conn.shutdown(socket.SHUT_RDWR)

    def close(self) -> None:
        """Stop accepting, close all connections and join the threads (idempotent)."""
        self._stop.set()
        self.disconnect_clients()
        for thread in self._threads:
            thread.join(timeout=5.0)
        if self._listener is not None:
            self._listener.close()
            self._listener = None

    def __enter__(self) -> ModbusTcpServer:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def _accept_loop(self) -> None:
        while not self._stop.is_set():
            try:
                conn, _ = self._listener.accept()
            except TimeoutError:
                continue
            except OSError:
                return
            conn.settimeout(0.1)
            conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            with self._conn_lock:
                self._connections.add(conn)
                self.connections_accepted += 1
            thread = threading.Thread(target=self._serve, args=(conn,), name="modbus-conn", daemon=True)
            thread.start()
            self._threads = [t for t in self._threads if t.is_alive()] + [thread]

    def _recv_exact(self, conn: socket.socket, n: int) -> bytes | None:
        data = bytearray()
        while len(data) < n:
            if self._stop.is_set():
                return None
            try:
                chunk = conn.recv(n - len(data))
            except TimeoutError:
                continue
            except OSError:
                return None
            if not chunk:
                return None
            data.extend(chunk)
        return bytes(data)

    def _serve(self, conn: socket.socket) -> None:
        try:
            while not self._stop.is_set():
                header = self._recv_exact(conn, MBAP_BYTES)
                if header is None:
                    return
                try:
                    length = parse_mbap(header).length
                except ModbusFrameError as err:
                    log.warning("modbus_bad_frame", error=str(err))
                    return
                pdu = self._recv_exact(conn, length - 1)
                if pdu is None:
                    return
                try:
                    response = self.protocol.handle_adu(header + pdu)
                except ModbusFrameError as err:
                    log.warning("modbus_bad_frame", error=str(err))
                    return
                if response is None:
                    log.info("modbus_connection_dropped_by_fault_injection")
                    return
                if self.faults.response_delay_s:
                    time.sleep(self.faults.response_delay_s)
                conn.sendall(response)
        except OSError:
            return
        finally:
            with self._conn_lock:
                self._connections.discard(conn)
            with contextlib.suppress(OSError):
                conn.close()


class ModbusRtuServer:
    """Modbus RTU on a pseudo-terminal (``path``): the same register map for serial-line drivers.

    A request with a bad CRC or another device address gets no answer (as on a real RS-485 line); a
    "dropped connection" from the fault injector is a request left unanswered.
    """

    def __init__(
        self,
        controller: SimulatedController,
        *,
        device_id: int | None = None,
        faults: ModbusFaultInjector | None = None,
        register_map: RegisterMap | None = None,
    ) -> None:
        self.controller = controller
        self.faults = faults or ModbusFaultInjector(controller.config.modbus_faults)
        self.device_id = device_id or controller.config.device_id
        self.protocol = ModbusProtocol(ControllerRegisterMap(controller, register_map), self.device_id, self.faults)
        self.crc_errors = 0
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._master = self._slave = -1
        self._wake_r = self._wake_w = -1
        self.path = ""

    @property
    def writes(self) -> list[ExecutedWrite]:
        return self.protocol.writes

    def start(self) -> ModbusRtuServer:
        import tty

        self._master, self._slave = os.openpty()
        tty.setraw(self._slave)
        os.set_blocking(self._master, False)
        self.path = os.ttyname(self._slave)
        self._wake_r, self._wake_w = os.pipe()
        self._thread = threading.Thread(target=self._run, name="modbus-rtu", daemon=True)
        self._thread.start()
        log.info("modbus_rtu_server_started", path=self.path)
        return self

    def close(self) -> None:
        if self._thread is None:
            return
        self._stop.set()
        os.write(self._wake_w, b"x")
        self._thread.join(timeout=5.0)
        self._thread = None
        for fd in (self._master, self._slave, self._wake_r, self._wake_w):
            with contextlib.suppress(OSError):
                os.close(fd)

    def __enter__(self) -> ModbusRtuServer:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def _run(self) -> None:
        buffer = bytearray()
        last_byte_s = time.monotonic()
        while not self._stop.is_set():
            timeout = RTU_GAP_S if buffer else 0.1
            readable, _, _ = select.select([self._master, self._wake_r], [], [], timeout)
            now = time.monotonic()
            if self._master in readable:
                with contextlib.suppress(BlockingIOError, InterruptedError, OSError):
                    chunk = os.read(self._master, 512)
                    buffer.extend(chunk)
                    last_byte_s = now
            quiet = now - last_byte_s >= RTU_GAP_S
            while buffer:
                length = rtu_request_length(bytes(buffer))
                if length == -1 or (length is None and quiet) or (length is not None and length > 260):
                    if not quiet:
                        break
                    length = len(buffer)
                if length is None or len(buffer) < length:
                    if quiet:
                        buffer.clear()
                    break
                frame = bytes(buffer[:length])
                del buffer[:length]
                self._handle(frame)

    def _handle(self, frame: bytes) -> None:
        try:
            address, pdu = rtu_split(frame)
        except ModbusFrameError:
            self.crc_errors += 1
            return
        if address not in (self.device_id, 0) or not pdu:
            return
        response = self.protocol.handle_pdu(pdu)
        if response is None or address == 0:
            return
        with contextlib.suppress(OSError):
            os.write(self._master, rtu_frame(address, response))
