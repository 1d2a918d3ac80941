"""The simulated controller's Modbus personality: its register map and transport-free request handling.

``ControllerRegisterMap`` maps the registers of ``hilcal/protocols/registers.py`` onto the ``SimulatedController``;
``ModbusProtocol`` turns a request (PDU or TCP ADU) into its response, with fault injection applied.
"""

from __future__ import annotations

import struct
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import structlog

from hilcal.protocols.compensation import COMP_BACKUP_BANK, COMP_LIVE_BANK, COMP_SAVED_BANK, COMP_STAGING_BANK
from hilcal.protocols.registers import (
    BACKUP_BANK,
    BACKUP_COMP_CRC32_REG,
    BACKUP_CRC32_REG,
    CAPABILITIES_REG,
    COMMIT_COUNTER_REG,
    CONTROLLER_STATE_REG,
    FAULT_CODE_REG,
    FIRMWARE_VERSION_REG,
    LEG_FORCES_REG,
    LEG_TEMPERATURE_REG,
    LIVE_BANK,
    LIVE_COMP_CRC32_REG,
    LIVE_CRC32_REG,
    MAGIC,
    MAGIC_REG,
    PARAM_COMMAND_REG,
    PARAM_STATUS_REG,
    PARAMETER_COUNT,
    PARAMETER_COUNT_REG,
    PROTOCOL_VERSION_REG,
    SAVE_COUNTER_REG,
    SAVED_BANK,
    SAVED_COMP_CRC32_REG,
    SAVED_CRC32_REG,
    SERIAL_NUMBER_REG,
    STAGED_COMP_CRC32_REG,
    STAGED_CRC32_REG,
    STAGED_LENGTH_REG,
    STAGED_WRITTEN_REG,
    STAGING_BANK,
    Capability,
    ModbusExceptionCode,
    ParamCommand,
    Register,
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
            (PROTOCOL_VERSION_REG, lambda: [c.protocol_version]),
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
        caps = c.capabilities
        if Capability.COMPENSATION in caps:
            self._readers += [
                (STAGED_COMP_CRC32_REG, lambda: [c.param_registers()["staged_comp_crc_hi"],
                                                 c.param_registers()["staged_comp_crc_lo"]]),
                (LIVE_COMP_CRC32_REG, lambda: split_u32(c.comp_crc32("live"))),
                (BACKUP_COMP_CRC32_REG, lambda: split_u32(c.comp_crc32("backup"))),
                (SAVED_COMP_CRC32_REG, lambda: split_u32(c.comp_crc32("saved"))),
                (COMP_LIVE_BANK, lambda: c.comp_words("live")),
                (COMP_STAGING_BANK, lambda: c.comp_words("staging")),
                (COMP_BACKUP_BANK, lambda: c.comp_words("backup")),
                (COMP_SAVED_BANK, lambda: c.comp_words("saved")),
            ]
        if Capability.FORCE_READING in caps:
            self._readers.append((LEG_FORCES_REG, lambda: words_from_floats(c.leg_forces_reading().tolist())))
        if Capability.TEMPERATURE_READING in caps:
            self._readers.append((LEG_TEMPERATURE_REG, lambda: words_from_floats([c.temperature_reading()])))
        self._comp_writable = Capability.COMPENSATION in caps

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
        header_end = STAGED_COMP_CRC32_REG.end if self._comp_writable else STAGED_CRC32_REG.end
        if STAGED_LENGTH_REG.address <= address and end <= header_end:
            words: list[int | None] = [None] * (STAGED_COMP_CRC32_REG.end - STAGED_LENGTH_REG.address)
            for k, v in enumerate(values):
                words[address - STAGED_LENGTH_REG.address + k] = v
            c.write_staging_header(words[0], words[1:3], words[3:5])
            return
        if self._comp_writable and COMP_STAGING_BANK.address <= address and end <= COMP_STAGING_BANK.end:
            try:
                c.write_comp_staging(address - COMP_STAGING_BANK.address, values)
            except StagingWriteRefused as err:
                raise ModbusError(ModbusExceptionCode.ILLEGAL_DATA_ADDRESS, str(err)) from None
            return
        if STAGING_BANK.address <= address and end <= STAGING_BANK.end:
            try:
                c.write_staging(address - STAGING_BANK.address, values)
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
