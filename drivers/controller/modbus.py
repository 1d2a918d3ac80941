"""Modbus driver of the controller's parameter interface (pymodbus client; Modbus TCP or RTU).

``ControllerParams.upload`` is a transaction (see docs/protocols.md): refuse unless the controller is
DISABLED; OPEN_STAGING; write the staging banks in chunks of at most 123 registers (the geometry and, on a
register-map 1.1 controller, the compensation block); write STAGED_LENGTH, STAGED_CRC32 and STAGED_COMP_CRC32; read
staging back and compare; COMMIT (the controller checks length, CRCs and limits and swaps geometry and block
atomically, keeping the previous pair as backup); read live back and compare. Saving to non-volatile memory is a
separate explicit step (``save``); ``rollback`` swaps live and backup (both). Requests are never retried
(retries=0): a write whose answer was lost may have been executed, so the caller starts a new upload, which
re-opens staging. Every operation returns (or attaches to its exception) an ``UploadRecord`` of each write,
the hashes of the sets involved, timestamps and read-back results; ``records`` keeps them all.
"""

from __future__ import annotations

import hashlib
from collections.abc import Callable, Sequence
from typing import TYPE_CHECKING, Any, Literal

import numpy as np
import structlog

from drivers.controller.base import ParameterInterface
from drivers.controller.parameter_sets import (
    CapabilityError,
    CompensationBlock,
    Identity,
    IdentityError,
    ModbusExceptionResponse,
    ModbusTransportError,
    NotDisabled,
    ParameterSet,
    ParameterValidationError,
    ParamsError,
    ReadbackMismatch,
    UploadRecord,
    UploadRefused,
    WriteRecord,
    now_utc,
)
from hilcal.protocols.compensation import COMP_BACKUP_BANK, COMP_LIVE_BANK, COMP_SAVED_BANK, COMP_STAGING_BANK
from hilcal.protocols.controller_states import ControllerState
from hilcal.protocols.registers import (
    BACKUP_BANK,
    CAPABILITIES_REG,
    CONTROLLER_STATE_REG,
    L0_INDEX,
    L0_REGISTERS,
    LEG_FORCES_REG,
    LEG_TEMPERATURE_REG,
    LIVE_BANK,
    LIVE_COMP_CRC32_REG,
    LIVE_CRC32_REG,
    MAGIC,
    MAGIC_REG,
    MAX_READ_REGISTERS,
    MAX_WRITE_REGISTERS,
    PARAM_COMMAND_REG,
    PARAM_STATUS_REG,
    PARAMETER_COUNT,
    PARAMETER_COUNT_REG,
    PARAMETER_REGISTERS,
    REGISTERS_PER_FLOAT,
    SAVED_BANK,
    STAGED_LENGTH_REG,
    STAGING_BANK,
    Capability,
    ParamCommand,
    ParamStatus,
    Register,
    crc32_of_words,
    floats_from_words,
    join_u32,
    split_u32,
    words_to_bytes,
)

if TYPE_CHECKING:
    from pymodbus.client import ModbusSerialClient, ModbusTcpClient

__all__ = [
    "CapabilityError", "CompensationBlock", "ControllerParams", "Identity", "IdentityError", "ModbusExceptionResponse",
    "ModbusTransportError", "NotDisabled", "ParameterSet", "ParameterValidationError", "ParamsError",
    "ReadbackMismatch", "UploadRecord", "UploadRefused", "WriteRecord",
]

log = structlog.get_logger(__name__)

DEFAULT_CHUNK_REGISTERS = 64
IDENTITY_REGISTERS = PARAMETER_COUNT_REG.end - MAGIC_REG.address
CAPABILITY_MASK = 0x007F


def _sha(words: Sequence[int]) -> str:
    return hashlib.sha256(words_to_bytes(words)).hexdigest()


class ControllerParams(ParameterInterface):
    """The controller's Modbus parameter interface; TCP (``host``/``port``) or RTU (``serial_port``)."""

    def __init__(
        self,
        host: str | None = None,
        port: int = 502,
        *,
        serial_port: str | None = None,
        baudrate: int = 115200,
        device_id: int = 1,
        timeout_s: float = 1.0,
        chunk_registers: int = DEFAULT_CHUNK_REGISTERS,
    ) -> None:
        if (host is None) == (serial_port is None):
            raise ValueError("give either host (Modbus TCP) or serial_port (Modbus RTU)")
        if not 1 <= chunk_registers <= MAX_WRITE_REGISTERS:
            raise ValueError(f"chunk_registers must be 1..{MAX_WRITE_REGISTERS}")
        from pymodbus import FramerType  # here, not at the top: the records and the engine use only the models
        from pymodbus.client import ModbusSerialClient, ModbusTcpClient

        self.device_id = device_id
        self.chunk_registers = chunk_registers
        self.records: list[UploadRecord] = []
        self._client: ModbusTcpClient | ModbusSerialClient
        if host is not None:
            self.endpoint = f"tcp://{host}:{port}"
            self._client = ModbusTcpClient(host, port=port, timeout=timeout_s, retries=0)
        else:
            assert serial_port is not None
            self.endpoint = f"rtu://{serial_port}@{baudrate}"
            self._client = ModbusSerialClient(
                serial_port, framer=FramerType.RTU, baudrate=baudrate, timeout=timeout_s, retries=0
            )

    def close(self) -> None:
        self._client.close()

    # ------------------------------------------------------------------ requests

    def _request(self, what: str, call: Callable[..., Any], address: int, **kwargs: Any) -> Any:
        from pymodbus.exceptions import ModbusException

        try:
            response = call(address, device_id=self.device_id, **kwargs)
        except ModbusException as err:
            self._client.close()
            raise ModbusTransportError(f"{what} at 0x{address:04X}: {err}") from err
        if response.isError():
            code = int(getattr(response, "exception_code", 0))
            raise ModbusExceptionResponse(
                f"{what} at 0x{address:04X}: Modbus exception {code}", response.function_code & 0x7F, address, code
            )
        return response

    def _read(self, address: int, count: int) -> list[int]:
        out: list[int] = []
        for start in range(address, address + count, MAX_READ_REGISTERS):
            n = min(MAX_READ_REGISTERS, address + count - start)
            response = self._request("read", self._client.read_holding_registers, start, count=n)
            registers = list(response.registers)
            if len(registers) != n:
                self._client.close()
                raise ModbusTransportError(f"read at 0x{start:04X}: {len(registers)} registers instead of {n}")
            out.extend(registers)
        return out

    def _read_block(self, reg: Register) -> list[int]:
        return self._read(reg.address, reg.count)

    def _write(self, record: UploadRecord | None, address: int, values: Sequence[int]) -> None:
        single = len(values) == 1
        entry = WriteRecord(
            function="write_register" if single else "write_registers", address=address, count=len(values), at=now_utc()
        )
        if record is not None:
            record.writes.append(entry)
        try:
            if single:
                self._request("write", self._client.write_register, address, value=int(values[0]))
            else:
                self._request("write", self._client.write_registers, address, values=[int(v) for v in values])
        except ParamsError as err:
            entry.error = str(err)
            raise
        entry.ok = True

    # ------------------------------------------------------------------ reads

    def read_identity(self) -> Identity:
        words = self._read(MAGIC_REG.address, IDENTITY_REGISTERS)
        identity = Identity(
            magic=words[0],
            protocol_version=words[1],
            firmware_version=words[2],
            serial_number=join_u32(words[3:5]),
            capabilities=Capability(words[CAPABILITIES_REG.address] & CAPABILITY_MASK),
            parameter_count=words[6],
        )
        if identity.magic != MAGIC or identity.parameter_count != PARAMETER_COUNT:
            raise IdentityError(
                f"not a compatible controller: magic 0x{identity.magic:04X} (expected 0x{MAGIC:04X}), "
                f"{identity.parameter_count} parameters (expected {PARAMETER_COUNT})"
            )
        return identity

    def read_state(self) -> ControllerState:
        value = self._read_block(CONTROLLER_STATE_REG)[0]
        try:
            return ControllerState(value)
        except ValueError:
            raise IdentityError(f"controller state register holds unknown value {value}") from None

    def read_status(self) -> ParamStatus:
        value = self._read_block(PARAM_STATUS_REG)[0]
        try:
            return ParamStatus(value)
        except ValueError:
            raise IdentityError(f"PARAM_STATUS holds unknown value {value}") from None

    def read_live(self) -> ParameterSet:
        return ParameterSet.from_words(self._read_block(LIVE_BANK))

    def read_backup(self) -> ParameterSet:
        return ParameterSet.from_words(self._read_block(BACKUP_BANK))

    def read_saved(self) -> ParameterSet:
        return ParameterSet.from_words(self._read_block(SAVED_BANK))

    def read_live_compensation(self) -> CompensationBlock:
        """The compensation block in use (register map 1.1 only)."""
        return CompensationBlock.from_words(self._read_block(COMP_LIVE_BANK))

    def read_saved_compensation(self) -> CompensationBlock:
        return CompensationBlock.from_words(self._read_block(COMP_SAVED_BANK))

    def read_leg_forces_kn(self) -> np.ndarray:
        """Each leg's axial compression as the controller reads it (kN; FORCE_READING only)."""
        return np.asarray(floats_from_words(self._read_block(LEG_FORCES_REG)), dtype=float)

    def read_temperature_c(self) -> float:
        """The leg temperature as the controller reads it (°C; TEMPERATURE_READING only)."""
        return float(floats_from_words(self._read_block(LEG_TEMPERATURE_REG))[0])

    # ------------------------------------------------------------------ transactions

    def _begin(self, operation: Literal["upload", "rollback", "save"]) -> tuple[UploadRecord, Identity]:
        record = UploadRecord(operation=operation, endpoint=self.endpoint, device_id=self.device_id,
                              started_at=now_utc())
        self.records.append(record)
        try:
            identity = self.read_identity()
            record.identity = identity.as_dict()
            record.offsets_only = identity.offsets_only
            state = self.read_state()
            if state is not ControllerState.DISABLED:
                raise NotDisabled(f"controller is {state.name}: parameters change only while DISABLED; "
                                  "nothing written")
            live = self._read_block(LIVE_BANK)
            record.previous_live_crc32 = f"{crc32_of_words(live):08x}"
            record.previous_live_sha256 = _sha(live)
            if identity.compensation:
                comp = self._read_block(COMP_LIVE_BANK)
                record.previous_compensation_sha256 = _sha(comp)
                record.previous_compensation_crc32 = f"{crc32_of_words(comp):08x}"
        except ParamsError as err:
            self._finish(record, err)
            raise
        return record, identity

    def _finish(
        self,
        record: UploadRecord,
        err: ParamsError | None,
        outcome: Literal["committed", "rolled_back", "saved"] = "committed",
    ) -> None:
        record.finished_at = now_utc()
        if err is None:
            record.outcome = outcome
            log.info("controller_params", operation=record.operation, outcome=record.outcome,
                     crc32=record.params_crc32, writes=len(record.writes))
            return
        record.outcome = "refused" if isinstance(err, NotDisabled | CapabilityError | UploadRefused |
                                                 ParameterValidationError | IdentityError) else "failed"
        record.error = f"{type(err).__name__}: {err}"
        err.record = record
        log.warning("controller_params", operation=record.operation, outcome=record.outcome, error=record.error)

    def _command(self, record: UploadRecord, command: ParamCommand) -> None:
        self._write(record, PARAM_COMMAND_REG.address, [int(command)])
        status = self.read_status()
        record.controller_status = status.name
        if status is not ParamStatus.OK:
            raise UploadRefused(f"controller refused {command.name}: {status.name}", status)

    def _geometry_blocks(self, identity: Identity, live: ParameterSet, target: ParameterSet
                         ) -> list[tuple[int, list[int]]]:
        """(offset, registers) chunks of the geometry staging bank this controller takes."""
        words = target.to_words()
        if identity.offsets_only:
            if not np.array_equal(live.to_vector()[:L0_INDEX], target.to_vector()[:L0_INDEX]):
                raise CapabilityError("offsets-only controller: this set changes a/b joint coordinates; only "
                                      "the six leg offsets l0 can be written; nothing written")
            first = L0_INDEX * REGISTERS_PER_FLOAT
            return [(k, words[k:min(k + self.chunk_registers, first + L0_REGISTERS)])
                    for k in range(first, first + L0_REGISTERS, self.chunk_registers)]
        if Capability.FULL_GEOMETRY in identity.capabilities:
            return [(k, words[k:k + self.chunk_registers]) for k in range(0, PARAMETER_REGISTERS,
                                                                             self.chunk_registers)]
        raise CapabilityError(f"controller capabilities {identity.capabilities!r} allow no parameter writes")

    @staticmethod
    def _check_compensation(identity: Identity, block: CompensationBlock) -> None:
        if not identity.compensation:
            raise CapabilityError("this controller (register map 1.0) has no compensation block: upload the "
                                  "geometry alone; nothing written")
        missing = block.needs() & ~identity.capabilities
        if missing:
            raise CapabilityError(f"the compensation block needs {missing.name}, which this controller does not "
                                  "have; nothing written")

    def upload(self, params: ParameterSet | Sequence[float] | np.ndarray, *, save: bool = False,
               compensation: CompensationBlock | None = None) -> UploadRecord:
        """Write, verify and commit a parameter set, and with it a compensation block when one is given (see the
        module docstring); save=True also saves them. Without a block the controller keeps its own."""
        target = params if isinstance(params, ParameterSet) else ParameterSet.from_vector(params)
        target = target.as_float32()
        words = target.to_words()
        comp_words = None if compensation is None else compensation.as_float32().to_words()
        record, identity = self._begin("upload")
        record.params_sha256 = target.sha256()
        record.params_crc32 = f"{target.crc32():08x}"
        try:
            blocks = self._geometry_blocks(identity, self.read_live(), target)
            comp_blocks: list[tuple[int, list[int]]] = []
            if compensation is not None and comp_words is not None:
                self._check_compensation(identity, compensation)
                record.compensation_sha256 = _sha(comp_words)
                record.compensation_crc32 = f"{crc32_of_words(comp_words):08x}"
                comp_blocks = [(k, comp_words[k:k + self.chunk_registers])
                               for k in range(0, len(comp_words), self.chunk_registers)]
            record.staged_registers = sum(len(b) for _, b in blocks) + sum(len(b) for _, b in comp_blocks)
            self._command(record, ParamCommand.OPEN_STAGING)
            for offset, block in blocks:
                self._write(record, STAGING_BANK.address + offset, block)
            for offset, block in comp_blocks:
                self._write(record, COMP_STAGING_BANK.address + offset, block)
            header = [record.staged_registers, *split_u32(target.crc32())]
            if comp_words is not None:
                header += split_u32(crc32_of_words(comp_words))
            self._write(record, STAGED_LENGTH_REG.address, header)
            self._compare(record, "staging", self._read_block(STAGING_BANK), words)
            if comp_words is not None:
                self._compare(record, "compensation staging", self._read_block(COMP_STAGING_BANK), comp_words)
            self._command(record, ParamCommand.COMMIT)
            live_after = self._read_block(LIVE_BANK)
            live_crc = join_u32(self._read_block(LIVE_CRC32_REG))
            record.live_after_sha256 = _sha(live_after)
            record.live_readback_match = live_after == words and live_crc == target.crc32()
            if comp_words is not None:
                comp_after = self._read_block(COMP_LIVE_BANK)
                comp_crc = join_u32(self._read_block(LIVE_COMP_CRC32_REG))
                record.compensation_readback_match = comp_after == comp_words and comp_crc == crc32_of_words(
                    comp_words)
                record.live_readback_match = record.live_readback_match and record.compensation_readback_match
            if not record.live_readback_match:
                raise ReadbackMismatch("live set read back after COMMIT differs from the uploaded set")
            if save:
                self._save_steps(record, identity)
        except ParamsError as err:
            self._finish(record, err)
            raise
        self._finish(record, None, "committed")
        return record

    @staticmethod
    def _compare(record: UploadRecord, what: str, read: list[int], written: list[int]) -> None:
        match = read == written
        if what == "staging":
            record.staging_readback_match = match
        else:
            record.staging_readback_match = bool(record.staging_readback_match) and match
        if not match:
            bad = [k for k, (a, b) in enumerate(zip(read, written, strict=True)) if a != b]
            raise ReadbackMismatch(f"{what} read-back differs at registers {bad[:8]}; not committed")

    def _save_steps(self, record: UploadRecord, identity: Identity) -> None:
        self._command(record, ParamCommand.SAVE)
        record.saved_readback_match = self._read_block(SAVED_BANK) == self._read_block(LIVE_BANK)
        if identity.compensation:
            record.saved_readback_match = record.saved_readback_match and (
                self._read_block(COMP_SAVED_BANK) == self._read_block(COMP_LIVE_BANK))
        if not record.saved_readback_match:
            raise ReadbackMismatch("non-volatile set read back after SAVE differs from the live set")
        record.saved = True

    def save(self) -> UploadRecord:
        """Copy the live set (and block) to non-volatile memory (controller DISABLED) and verify it."""
        record, identity = self._begin("save")
        try:
            self._save_steps(record, identity)
        except ParamsError as err:
            self._finish(record, err)
            raise
        self._finish(record, None, "saved")
        return record

    def rollback(self, last_upload: UploadRecord | None = None) -> UploadRecord:
        """Swap live and backup, geometry and block together (controller DISABLED): undoes the last commit
        (``last_upload`` is not needed: the controller keeps the backup)."""
        record, identity = self._begin("rollback")
        try:
            backup = self._read_block(BACKUP_BANK)
            comp_backup = self._read_block(COMP_BACKUP_BANK) if identity.compensation else None
            self._command(record, ParamCommand.ROLLBACK)
            live_after = self._read_block(LIVE_BANK)
            record.live_after_sha256 = _sha(live_after)
            record.params_sha256 = _sha(backup)
            record.params_crc32 = f"{crc32_of_words(backup):08x}"
            record.live_readback_match = live_after == backup
            if comp_backup is not None:
                record.compensation_sha256 = _sha(comp_backup)
                record.compensation_readback_match = self._read_block(COMP_LIVE_BANK) == comp_backup
                record.live_readback_match = record.live_readback_match and record.compensation_readback_match
            if not record.live_readback_match:
                raise ReadbackMismatch("live set after ROLLBACK is not the former backup")
        except ParamsError as err:
            self._finish(record, err)
            raise
        self._finish(record, None, "rolled_back")
        return record
