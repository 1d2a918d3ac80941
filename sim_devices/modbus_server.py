"""The simulated controller's Modbus parameter interface: small Modbus TCP and RTU servers of our own.

Function codes 3 (read holding registers), 6 (write single) and 16 (write multiple) with MBAP framing (TCP)
or address + CRC-16 framing on a pseudo-terminal (RTU) and exception responses, over the register map of
``hilcal/protocols/registers.py``. Written from the Modbus
Application Protocol v1.1b3 rather than on pymodbus' server datastore (whose API changed in 3.13), so the
driver's pymodbus client is tested against an independent peer. ``ModbusFaultInjector`` answers with
exceptions and drops connections, e.g. in the middle of an upload.
"""

from __future__ import annotations

import contextlib
import os
import select
import socket
import struct
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import structlog

from hilcal.protocols.checksums import crc16_modbus
from hilcal.protocols.registers import (
    BACKUP_BANK,
    BACKUP_CRC32_REG,
    CAPABILITIES_REG,
    COMMIT_COUNTER_REG,
    CONTROLLER_STATE_REG,
    FAULT_CODE_REG,
    FIRMWARE_VERSION_REG,
    LIVE_BANK,
    LIVE_CRC32_REG,
    MAGIC,
    MAGIC_REG,
    MAX_READ_REGISTERS,
    MAX_WRITE_REGISTERS,
    PARAM_COMMAND_REG,
    PARAM_STATUS_REG,
    PARAMETER_COUNT,
    PARAMETER_COUNT_REG,
    PROTOCOL_VERSION,
    PROTOCOL_VERSION_REG,
    SAVE_COUNTER_REG,
    SAVED_BANK,
    SAVED_CRC32_REG,
    SERIAL_NUMBER_REG,
    STAGED_CRC32_REG,
    STAGED_LENGTH_REG,
    STAGED_WRITTEN_REG,
    STAGING_BANK,
    ModbusExceptionCode,
    ParamCommand,
    Register,
    split_u32,
)
from sim_devices.controller import ModbusFaultConfig, SimulatedController, StagingWriteRefused

log = structlog.get_logger(__name__)

READ_HOLDING = 0x03
WRITE_SINGLE = 0x06
WRITE_MULTIPLE = 0x10
MBAP_BYTES = 7
MAX_PDU_BYTES = 253


class ModbusFrameError(ValueError):
    """Bytes that are not a Modbus TCP frame; the server closes the connection (no response is possible)."""


class ModbusError(Exception):
    """A request answered with a Modbus exception response."""

    def __init__(self, code: ModbusExceptionCode, message: str = "") -> None:
        super().__init__(f"{code.name}: {message}" if message else code.name)
        self.code = code


@dataclass(frozen=True)
class MbapHeader:
    transaction_id: int
    protocol_id: int
    length: int
    unit_id: int


def parse_mbap(header: bytes) -> MbapHeader:
    """Parse the 7-byte MBAP header; ``length`` counts the unit ID and the PDU (2..254)."""
    if len(header) != MBAP_BYTES:
        raise ModbusFrameError(f"MBAP header needs {MBAP_BYTES} bytes, got {len(header)}")
    tid, pid, length, unit = struct.unpack(">HHHB", header)
    if pid != 0:
        raise ModbusFrameError(f"protocol identifier {pid} is not 0 (Modbus)")
    if not 2 <= length <= MAX_PDU_BYTES + 1:
        raise ModbusFrameError(f"MBAP length {length} outside 2..{MAX_PDU_BYTES + 1}")
    return MbapHeader(tid, pid, length, unit)


@dataclass(frozen=True)
class ModbusRequest:
    function: int
    address: int
    count: int
    values: tuple[int, ...] = ()

    @property
    def is_write(self) -> bool:
        return self.function in (WRITE_SINGLE, WRITE_MULTIPLE)


def decode_request_pdu(pdu: bytes) -> ModbusRequest:
    """Decode a request PDU; ModbusError for what deserves an exception response, ModbusFrameError if empty."""
    if not pdu:
        raise ModbusFrameError("empty PDU")
    function, body = pdu[0], pdu[1:]
    if function == READ_HOLDING:
        if len(body) != 4:
            raise ModbusError(ModbusExceptionCode.ILLEGAL_DATA_VALUE, "FC3 needs address and quantity")
        address, count = struct.unpack(">HH", body)
        if not 1 <= count <= MAX_READ_REGISTERS:
            raise ModbusError(ModbusExceptionCode.ILLEGAL_DATA_VALUE, f"quantity {count} outside 1..125")
        return ModbusRequest(function, address, count)
    if function == WRITE_SINGLE:
        if len(body) != 4:
            raise ModbusError(ModbusExceptionCode.ILLEGAL_DATA_VALUE, "FC6 needs address and value")
        address, value = struct.unpack(">HH", body)
        return ModbusRequest(function, address, 1, (value,))
    if function == WRITE_MULTIPLE:
        if len(body) < 5:
            raise ModbusError(ModbusExceptionCode.ILLEGAL_DATA_VALUE, "FC16 too short")
        address, count, byte_count = struct.unpack(">HHB", body[:5])
        if not 1 <= count <= MAX_WRITE_REGISTERS or byte_count != 2 * count or len(body) != 5 + byte_count:
            raise ModbusError(ModbusExceptionCode.ILLEGAL_DATA_VALUE, "FC16 quantity/byte count mismatch")
        values = struct.unpack(f">{count}H", body[5:])
        return ModbusRequest(function, address, count, values)
    raise ModbusError(ModbusExceptionCode.ILLEGAL_FUNCTION, f"function code {function}")


def exception_pdu(function: int, code: ModbusExceptionCode) -> bytes:
    return bytes(((function | 0x80) & 0xFF, int(code)))


class ControllerRegisterMap:
    """Register reads and writes mapped onto the controller model (see hilcal.protocols.registers)."""

    def __init__(self, controller: SimulatedController) -> None:
        self.controller = controller
        c = controller
        cfg = c.config

        def param(key: str) -> Callable[[], list[int]]:
            return lambda: [c.param_registers()[key]]

        self._readers: list[tuple[Register, Callable[[], list[int]]]] = [
            (MAGIC_REG, lambda: [MAGIC]),
            (PROTOCOL_VERSION_REG, lambda: [PROTOCOL_VERSION]),
            (FIRMWARE_VERSION_REG, lambda: [cfg.firmware_version]),
            (SERIAL_NUMBER_REG, lambda: split_u32(cfg.serial_number)),
            (CAPABILITIES_REG, lambda: [int(c.capabilities)]),
            (PARAMETER_COUNT_REG, lambda: [PARAMETER_COUNT]),
            (CONTROLLER_STATE_REG, lambda: [int(c.state)]),
            (FAULT_CODE_REG, lambda: [int(c.snapshot().fault)]),
            (PARAM_COMMAND_REG, lambda: [0]),
            (PARAM_STATUS_REG, param("status")),
            (COMMIT_COUNTER_REG, param("commit_counter")),
            (SAVE_COUNTER_REG, param("save_counter")),
            (STAGED_WRITTEN_REG, param("staged_written")),
            (LIVE_CRC32_REG, lambda: split_u32(c.bank_crc32("live"))),
            (BACKUP_CRC32_REG, lambda: split_u32(c.bank_crc32("backup"))),
            (SAVED_CRC32_REG, lambda: split_u32(c.bank_crc32("saved"))),
            (STAGED_LENGTH_REG, param("staged_length")),
            (STAGED_CRC32_REG, lambda: [c.param_registers()["staged_crc_hi"], c.param_registers()["staged_crc_lo"]]),
            (LIVE_BANK, lambda: c.bank_words("live")),
            (STAGING_BANK, lambda: c.bank_words("staging")),
            (BACKUP_BANK, lambda: c.bank_words("backup")),
            (SAVED_BANK, lambda: c.bank_words("saved")),
        ]

    def read(self, address: int, count: int) -> list[int]:
        """Values of ``count`` registers from ``address``; ILLEGAL_DATA_ADDRESS if any is unmapped."""
        cache: dict[str, list[int]] = {}
        out = []
        for addr in range(address, address + count):
            for reg, reader in self._readers:
                if reg.address <= addr < reg.end:
                    if reg.name not in cache:
                        cache[reg.name] = reader()
                    out.append(cache[reg.name][addr - reg.address])
                    break
            else:
                raise ModbusError(ModbusExceptionCode.ILLEGAL_DATA_ADDRESS, f"register 0x{addr:04X} is not mapped")
        return out

    def write(self, address: int, values: Sequence[int]) -> None:
        """Write registers; the range must lie inside one writable block, else nothing is written."""
        end = address + len(values)
        c = self.controller
        if address == PARAM_COMMAND_REG.address and len(values) == 1:
            try:
                command = ParamCommand(values[0])
            except ValueError:
                raise ModbusError(ModbusExceptionCode.ILLEGAL_DATA_VALUE, f"unknown command {values[0]}") from None
            c.param_command(command)
            return
        if STAGED_LENGTH_REG.address <= address and end <= STAGED_CRC32_REG.end:
            words: list[int | None] = [None] * 3
            for k, v in enumerate(values):
                words[address - STAGED_LENGTH_REG.address + k] = v
            c.write_staging_header(words[0], (words[1], words[2]))
            return
        if STAGING_BANK.address <= address and end <= STAGING_BANK.end:
            try:
                c.write_staging(address - STAGING_BANK.address, values)
            except StagingWriteRefused as err:
                raise ModbusError(ModbusExceptionCode.ILLEGAL_DATA_ADDRESS, str(err)) from None
            return
        raise ModbusError(ModbusExceptionCode.ILLEGAL_DATA_ADDRESS, f"registers 0x{address:04X}..0x{end - 1:04X}"
                          " are not writable as one block")


@dataclass
class _ExceptionRule:
    code: ModbusExceptionCode
    remaining: int
    function: int | None
    address: int | None
    skip: int = 0


@dataclass(frozen=True)
class FaultAction:
    """What the fault injector decided for one request."""

    kind: str = "pass"
    code: ModbusExceptionCode | None = None
    execute: bool = False


class ModbusFaultInjector:
    """Exception responses and dropped connections, switchable at start (ModbusFaultConfig) and at run time."""

    def __init__(self, config: ModbusFaultConfig | None = None) -> None:
        cfg = config or ModbusFaultConfig()
        self._lock = threading.Lock()
        self._rules: list[_ExceptionRule] = []
        self._corrupt_writes = 0
        self._drop_in: int | None = cfg.drop_after_writes
        self._drop_execute = cfg.execute_dropped_write
        self._always: ModbusExceptionCode | None = (
            ModbusExceptionCode(cfg.exception_code) if cfg.exception_code is not None else None
        )
        self.response_delay_s = cfg.response_delay_s

    def drop_connection_at_write(self, n: int, *, execute: bool = False) -> None:
        """Close the connection when the n-th write request from now arrives (1 = the next one), once.

        execute=True: that write is carried out before the connection closes (its response is lost).
        """
        if n < 1:
            raise ValueError("n counts from 1")
        with self._lock:
            self._drop_in = n
            self._drop_execute = execute

    def exception_next(
        self,
        code: ModbusExceptionCode,
        count: int = 1,
        *,
        function: int | None = None,
        address: int | None = None,
        skip: int = 0,
    ) -> None:
        """Answer ``count`` matching requests, after letting ``skip`` through, with an exception (not executed)."""
        with self._lock:
            self._rules.append(_ExceptionRule(code, count, function, address, skip))

    def corrupt_next_write(self, count: int = 1) -> None:
        """Flip the lowest bit of the first value of the next ``count`` FC16 requests (a flaky link/firmware)."""
        with self._lock:
            self._corrupt_writes += count

    def exception_always(self, code: ModbusExceptionCode | None) -> None:
        """Answer every request with this exception (None: back to normal)."""
        with self._lock:
            self._always = code

    def clear(self) -> None:
        with self._lock:
            self._rules.clear()
            self._corrupt_writes = 0
            self._drop_in = None
            self._always = None

    def decide(self, request: ModbusRequest) -> FaultAction:
        with self._lock:
            if self._always is not None:
                return FaultAction("exception", self._always)
            if request.is_write and self._drop_in is not None:
                self._drop_in -= 1
                if self._drop_in == 0:
                    self._drop_in = None
                    return FaultAction("drop", execute=self._drop_execute)
            for rule in self._rules:
                if rule.function in (None, request.function) and rule.address in (None, request.address):
                    if rule.skip > 0:
                        rule.skip -= 1
                        continue
                    rule.remaining -= 1
                    if rule.remaining <= 0:
                        self._rules.remove(rule)
                    return FaultAction("exception", rule.code)
            if request.function == WRITE_MULTIPLE and self._corrupt_writes > 0:
                self._corrupt_writes -= 1
                return FaultAction("corrupt")
            return FaultAction()


@dataclass(frozen=True)
class ExecutedWrite:
    function: int
    address: int
    count: int
    at_s: float


@dataclass
class ModbusProtocol:
    """Transport-independent request handling: PDU in, PDU out (or a connection drop)."""

    registers: ControllerRegisterMap
    device_id: int
    faults: ModbusFaultInjector
    writes: list[ExecutedWrite] = field(default_factory=list)
    requests: int = 0
    _lock: threading.Lock = field(default_factory=threading.Lock)

    def execute(self, request: ModbusRequest) -> bytes:
        if request.function == READ_HOLDING:
            values = self.registers.read(request.address, request.count)
            return struct.pack(f">BB{len(values)}H", READ_HOLDING, 2 * len(values), *values)
        self.registers.write(request.address, request.values)
        self.writes.append(ExecutedWrite(request.function, request.address, request.count, time.monotonic()))
        if request.function == WRITE_SINGLE:
            return struct.pack(">BHH", WRITE_SINGLE, request.address, request.values[0])
        return struct.pack(">BHH", WRITE_MULTIPLE, request.address, request.count)

    def handle_pdu(self, pdu: bytes) -> bytes | None:
        """Response PDU, or None when the connection must be dropped (fault injection)."""
        with self._lock:
            self.requests += 1
            try:
                request = decode_request_pdu(pdu)
            except ModbusError as err:
                return exception_pdu(pdu[0], err.code)
            action = self.faults.decide(request)
            if action.kind == "exception" and action.code is not None:
                return exception_pdu(request.function, action.code)
            if action.kind == "drop" and not action.execute:
                return None
            if action.kind == "corrupt":
                request = ModbusRequest(request.function, request.address, request.count,
                                        (request.values[0] ^ 1, *request.values[1:]))
            try:
                response = self.execute(request)
            except ModbusError as err:
                return exception_pdu(request.function, err.code)
            except Exception:
                log.exception("modbus_request_failed", function=request.function, address=request.address)
                return exception_pdu(request.function, ModbusExceptionCode.SERVER_DEVICE_FAILURE)
            return None if action.kind == "drop" else response

    def handle_adu(self, adu: bytes) -> bytes | None:
        """One complete Modbus TCP frame in, the response frame out (None: no response, drop the link)."""
        header = parse_mbap(adu[:MBAP_BYTES])
        pdu = adu[MBAP_BYTES:]
        if len(pdu) != header.length - 1:
            raise ModbusFrameError(f"MBAP length says {header.length - 1} PDU bytes, got {len(pdu)}")
        if header.unit_id not in (self.device_id, 0, 0xFF):
            response: bytes | None = exception_pdu(pdu[0], ModbusExceptionCode.GATEWAY_TARGET_FAILED)
        else:
            response = self.handle_pdu(pdu)
        if response is None:
            return None
        return struct.pack(">HHHB", header.transaction_id, 0, len(response) + 1, header.unit_id) + response


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
    ) -> None:
        self.controller = controller
        self.faults = faults or ModbusFaultInjector(controller.config.modbus_faults)
        self.protocol = ModbusProtocol(
            ControllerRegisterMap(controller), device_id or controller.config.device_id, self.faults
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


# ---------------------------------------------------------------------------------------------- RTU

RTU_GAP_S = 0.005
"""Silence that ends a frame whose length the function code does not tell (no real baud timing on a pty)."""


def rtu_request_length(buffer: bytes) -> int | None:
    """Length of the RTU request starting the buffer: an int, None if more bytes are needed, -1 if unknown."""
    if len(buffer) < 2:
        return None
    function = buffer[1]
    if function in (READ_HOLDING, WRITE_SINGLE):
        return 8
    if function == WRITE_MULTIPLE:
        return None if len(buffer) < 7 else 9 + buffer[6]
    return -1


def rtu_split(frame: bytes) -> tuple[int, bytes]:
    """(address, PDU) of an RTU frame; ModbusFrameError if too short or the CRC-16 (low byte first) is wrong."""
    if len(frame) < 4:
        raise ModbusFrameError(f"RTU frame of {len(frame)} bytes")
    if crc16_modbus(frame[:-2]) != int.from_bytes(frame[-2:], "little"):
        raise ModbusFrameError("RTU CRC-16 mismatch")
    return frame[0], frame[1:-2]


def rtu_frame(address: int, pdu: bytes) -> bytes:
    body = bytes([address]) + pdu
    return body + crc16_modbus(body).to_bytes(2, "little")


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
    ) -> None:
        self.controller = controller
        self.faults = faults or ModbusFaultInjector(controller.config.modbus_faults)
        self.device_id = device_id or controller.config.device_id
        self.protocol = ModbusProtocol(ControllerRegisterMap(controller), self.device_id, self.faults)
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
