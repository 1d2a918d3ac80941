"""The simulated controller's Modbus personality: its register map and transport-free request handling.

``ControllerRegisterMap`` maps the registers of a register map file (``hilcal.protocols.modbus_map``; hilcal's own
``hilcal-1.1`` by default) onto the ``SimulatedController``, with its own register encoding; ``ModbusProtocol``
turns a request (PDU or TCP ADU) into its response, with fault injection applied.
"""

from __future__ import annotations

import struct
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import structlog

from hilcal.protocols.compensation import BLOCK_REGISTERS
from hilcal.protocols.controller_states import ControllerState
from hilcal.protocols.modbus_map import RegisterMap, default_register_map
from hilcal.protocols.registers import (
    MAGIC,
    PARAMETER_COUNT,
    PARAMETER_REGISTERS,
    Capability,
    ModbusExceptionCode,
    ParamCommand,
    ParamStatus,
    split_u32,
    words_from_floats,
)
from sim_devices.controller.modbus_faults import ModbusFaultInjector
from sim_devices.controller.modbus_frames import (
    MBAP_BYTES,
    READ_HOLDING,
    WRITE_MULTIPLE,
    WRITE_SINGLE,
    ModbusError,
    ModbusFrameError,
    ModbusRequest,
    decode_request_pdu,
    exception_pdu,
    parse_mbap,
)
from sim_devices.controller.parameter_banks import StagingWriteRefused
from sim_devices.controller.state_machine import SimulatedController

log = structlog.get_logger(__name__)


Span = tuple[str, int, int]
"""(name, first address, register count)."""


def serviceable_problems(m: RegisterMap) -> list[str]:
    """What the simulated controller cannot serve in a map: it is a hilcal controller with staging banks, float32
    ABCD geometry in one 84-register run per bank, u16/u32 identity registers, every state mapped."""
    problems = []
    if not m.staged or m.device.word_order != "ABCD":
        problems.append("device: the simulated controller takes a staged transaction in word order ABCD")
    parts = m.parts()
    if len(parts) != 3:
        problems.append("geometry: the simulated controller holds a, b and l0")
    for p in parts:
        if (p.type, p.word_order, p.scale, p.offset) != ("f32", "ABCD", 1.0, 0.0):
            problems.append(f"geometry.{p.name}: the simulated controller holds float32 ABCD in mm")
        for bank, address in p.banks.items():
            if address is None or address != parts[0].banks[bank] + 2 * p.start:
                problems.append(f"geometry.{p.name}.{bank}: the simulated controller keeps each bank in one run")
    fields = [*(m.identity.fields().items() if m.identity else ()), *m.diagnostics.items()]
    problems += [f"{k}: the simulated controller serves u16 and u32 (ABCD)" for k, f in fields
                 if f.type not in ("u16", "u32") or m.word_order(f.word_order) != "ABCD"]
    problems += [f"diagnostics.{k}: not a register the simulated controller has" for k in m.diagnostics
                 if k not in ("commit_counter", "save_counter", "staged_written")]
    if m.state is None or m.state.type != "u16" or set(m.state.values()) != set(ControllerState):
        problems.append("state: the simulated controller needs a u16 state register with every state's value")
    return problems


class ControllerRegisterMap:
    """Register reads and writes mapped onto the controller model, at the addresses of a register map
    (``hilcal.protocols.modbus_map``; default ``hilcal-1.1``). The encoding is this module's own."""

    def __init__(self, controller: SimulatedController, register_map: RegisterMap | None = None) -> None:
        m = register_map or default_register_map()
        problems = serviceable_problems(m)
        if problems:
            raise ValueError(f"register map {m.device.name}: " + "; ".join(problems))
        self.map = m
        self.controller = c = controller
        cfg = c.config
        registers = c.param_registers

        def u32(value: Callable[[], int]) -> Callable[[], list[int]]:
            return lambda: split_u32(value())

        identity = {
            "magic": lambda: MAGIC, "protocol_version": lambda: c.protocol_version,
            "firmware_version": lambda: cfg.firmware_version, "serial_number": lambda: cfg.serial_number,
            "capabilities": lambda: int(c.capabilities), "parameter_count": lambda: PARAMETER_COUNT,
        }
        readers: list[tuple[Span, Callable[[], list[int]]]] = []
        for key, f in (m.identity.fields().items() if m.identity else ()):
            value = identity[key]
            readers.append(((key, f.address, f.count), u32(value) if f.count == 2 else (lambda v=value: [v()])))
        states = {state: raw[0] for state, raw in m.state.values().items()}  # type: ignore[union-attr]
        readers.append((("state", m.state.address, 1), lambda: [states[c.state]]))  # type: ignore[union-attr]
        if m.fault_code is not None:
            readers.append((("fault_code", m.fault_code.address, 1), lambda: [int(c.snapshot().fault)]))
        commands = m.commands.codes()  # type: ignore[union-attr]
        self._commands = {code: ParamCommand[name.upper()] for name, code in commands.items()}
        readers.append((("commands", m.commands.address, 1), lambda: [0]))  # type: ignore[union-attr]
        statuses = m.status.codes()  # type: ignore[union-attr]
        readers.append((("status", m.status.address, 1),  # type: ignore[union-attr]
                        lambda: [statuses.get(ParamStatus(registers()["status"]), 0xFFFF)]))
        for key, f in m.diagnostics.items():
            readers.append(((key, f.address, f.count), lambda k=key: [registers()[k]]))
        self._header: dict[int, tuple[str, int]] = {}
        if m.staging is not None and m.staging.length is not None:
            readers.append((("staged_length", m.staging.length, 1), lambda: [registers()["staged_length"]]))
            self._header[m.staging.length] = ("length", 0)
        sums = m.checksum
        if sums is not None:
            for bank in ("live", "backup", "saved"):
                if getattr(sums, bank) is not None:
                    readers.append(((f"{bank}_crc32", getattr(sums, bank), 2), u32(lambda b=bank: c.bank_crc32(b))))
            if sums.staged is not None:
                readers.append((("staged_crc32", sums.staged, 2),
                                lambda: [registers()["staged_crc_hi"], registers()["staged_crc_lo"]]))
                self._header.update({sums.staged: ("crc", 0), sums.staged + 1: ("crc", 1)})
        for bank, address in m.parts()[0].banks.items():
            readers.append(((bank, address, PARAMETER_REGISTERS), lambda b=bank: c.bank_words(b)))
        self._staging = m.parts()[0].banks["staging"]
        caps = c.capabilities
        self._comp_staging: int | None = None
        if Capability.COMPENSATION in caps and m.compensation is not None:
            comp = m.compensation
            for bank in ("live", "staging", "backup", "saved"):
                if getattr(comp, bank) is not None:
                    readers.append(((f"comp_{bank}", getattr(comp, bank), BLOCK_REGISTERS),
                                    lambda b=bank: c.comp_words(b)))
            self._comp_staging = comp.staging
            for bank in ("live", "backup", "saved"):
                address = getattr(comp.checksum, bank) if comp.checksum else None
                if address is not None:
                    readers.append(((f"comp_{bank}_crc32", address, 2), u32(lambda b=bank: c.comp_crc32(b))))
            if comp.checksum is not None and comp.checksum.staged is not None:
                readers.append((("staged_comp_crc32", comp.checksum.staged, 2),
                                lambda: [registers()["staged_comp_crc_hi"], registers()["staged_comp_crc_lo"]]))
                self._header.update({comp.checksum.staged: ("comp", 0), comp.checksum.staged + 1: ("comp", 1)})
        sensors = m.sensors
        if sensors is not None and sensors.leg_forces_kn is not None and Capability.FORCE_READING in caps:
            readers.append((("leg_forces", sensors.leg_forces_kn.address, 12),
                            lambda: words_from_floats(c.leg_forces_reading().tolist())))
        if sensors is not None and sensors.temperature_c is not None and Capability.TEMPERATURE_READING in caps:
            readers.append((("temperature", sensors.temperature_c.address, 2),
                            lambda: words_from_floats([c.temperature_reading()])))
        self._readers = readers

    def read(self, address: int, count: int) -> list[int]:
        """Values of ``count`` registers from ``address``; ILLEGAL_DATA_ADDRESS if any is unmapped."""
        cache: dict[str, list[int]] = {}
        out = []
        for addr in range(address, address + count):
            for (name, start, n), reader in self._readers:
                if start <= addr < start + n:
                    if name not in cache:
                        cache[name] = reader()
                    out.append(cache[name][addr - start])
                    break
            else:
                raise ModbusError(ModbusExceptionCode.ILLEGAL_DATA_ADDRESS, f"register 0x{addr:04X} is not mapped")
        return out

    def write(self, address: int, values: Sequence[int]) -> None:
        """Write registers; the range must lie inside one writable block, else nothing is written."""
        end = address + len(values)
        c = self.controller
        if address == self.map.commands.address and len(values) == 1:  # type: ignore[union-attr]
            command = self._commands.get(values[0])
            if command is None:
                raise ModbusError(ModbusExceptionCode.ILLEGAL_DATA_VALUE, f"unknown command {values[0]}")
            c.param_command(command)
            return
        if all(a in self._header for a in range(address, end)):
            header: dict[str, list[int | None]] = {"length": [None], "crc": [None, None], "comp": [None, None]}
            for a, v in zip(range(address, end), values, strict=True):
                kind, k = self._header[a]
                header[kind][k] = v
            c.write_staging_header(header["length"][0], header["crc"], header["comp"])
            return
        for start, size, write in ((self._comp_staging, BLOCK_REGISTERS, c.write_comp_staging),
                                   (self._staging, PARAMETER_REGISTERS, c.write_staging)):
            if start is not None and start <= address and end <= start + size:
                try:
                    write(address - start, values)
                except StagingWriteRefused as err:
                    raise ModbusError(ModbusExceptionCode.ILLEGAL_DATA_ADDRESS, str(err)) from None
                return
        raise ModbusError(ModbusExceptionCode.ILLEGAL_DATA_ADDRESS, f"registers 0x{address:04X}..0x{end - 1:04X}"
                          " are not writable as one block")


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
