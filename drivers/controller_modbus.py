"""Modbus driver of the controller's parameter interface (pymodbus client; Modbus TCP or RTU).

``ControllerParams.upload`` is a transaction (see docs/protocols.md): refuse unless the controller is
DISABLED; OPEN_STAGING; write the staging bank in chunks of at most 123 registers; write STAGED_LENGTH and
STAGED_CRC32; read staging back and compare; COMMIT (the controller checks length, CRC and limits and swaps
atomically, keeping the previous live set as backup); read live back and compare. Saving to non-volatile
memory is a separate explicit step (``save``); ``rollback`` swaps live and backup. Requests are never retried
(retries=0): a write whose answer was lost may have been executed, so the caller starts a new upload, which
re-opens staging. Every operation returns (or attaches to its exception) an ``UploadRecord`` of each write,
the hashes of the sets involved, timestamps and read-back results; ``records`` keeps them all.
"""

from __future__ import annotations

import hashlib
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from datetime import UTC, datetime
from typing import TYPE_CHECKING, Annotated, Any, Literal

import numpy as np
import structlog
from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator

from hilcal.protocols.controller_states import ControllerState
from hilcal.protocols.registers import (
    A_B_LIMIT_MM,
    BACKUP_BANK,
    CAPABILITIES_REG,
    CONTROLLER_STATE_REG,
    L0_INDEX,
    L0_MAX_MM,
    L0_MIN_MM,
    L0_REGISTERS,
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
    words_from_floats,
    words_to_bytes,
)
from hilcal.robot import Robot

if TYPE_CHECKING:
    from pymodbus.client import ModbusSerialClient, ModbusTcpClient

log = structlog.get_logger(__name__)

Vec3 = Annotated[list[float], Field(min_length=3, max_length=3)]
DEFAULT_CHUNK_REGISTERS = 64
IDENTITY_REGISTERS = PARAMETER_COUNT_REG.end - MAGIC_REG.address


class ParamsError(Exception):
    """Base class of parameter-interface errors; ``record`` is the UploadRecord of the failed operation."""

    record: UploadRecord | None = None


class ParameterValidationError(ParamsError, ValueError):
    """A parameter set that is not sane (non-finite, out of bounds, wrong shape); nothing was written."""


class ModbusTransportError(ParamsError):
    """The connection failed or timed out (e.g. dropped in the middle of an upload)."""


class ModbusExceptionResponse(ParamsError):
    """The controller answered a request with a Modbus exception."""

    def __init__(self, message: str, function: int, address: int, code: int) -> None:
        super().__init__(message)
        self.function = function
        self.address = address
        self.code = code


class IdentityError(ParamsError):
    """The device is not a compatible controller (magic or parameter count)."""


class NotDisabled(ParamsError):
    """Parameters can only change while the controller is DISABLED; nothing was written."""


class CapabilityError(ParamsError):
    """The controller cannot take this set (e.g. a/b change on an offsets-only controller); nothing written."""


class UploadRefused(ParamsError):
    """The controller refused a parameter command; ``status`` says why. The live set is unchanged."""

    def __init__(self, message: str, status: ParamStatus) -> None:
        super().__init__(message)
        self.status = status


class ReadbackMismatch(ParamsError):
    """A register block read back differs from what was written."""


def _check_finite(values: list[float], what: str, low: float, high: float) -> list[float]:
    for v in values:
        if not math.isfinite(v) or not low <= v <= high:
            raise ValueError(f"{what} value {v} outside [{low}, {high}] mm")
    return values


class ParameterSet(BaseModel):
    """The 42 controller parameters in mm: platform joints a, base joints b (6 x 3 each), leg offsets l0 (6)."""

    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)

    a_mm: Annotated[list[Vec3], Field(min_length=6, max_length=6)]
    b_mm: Annotated[list[Vec3], Field(min_length=6, max_length=6)]
    l0_mm: Annotated[list[float], Field(min_length=6, max_length=6)]

    @field_validator("a_mm", "b_mm")
    @classmethod
    def _joints(cls, v: list[list[float]]) -> list[list[float]]:
        for p in v:
            _check_finite(p, "joint coordinate", -A_B_LIMIT_MM, A_B_LIMIT_MM)
        return v

    @field_validator("l0_mm")
    @classmethod
    def _offsets(cls, v: list[float]) -> list[float]:
        return _check_finite(v, "leg offset", L0_MIN_MM, L0_MAX_MM)

    @classmethod
    def from_vector(cls, values: Sequence[float] | np.ndarray) -> ParameterSet:
        """From 42 values in register order: a (leg-major x, y, z), b, l0. ParameterValidationError if bad."""
        v = np.asarray(values, dtype=float)
        if v.shape != (PARAMETER_COUNT,):
            raise ParameterValidationError(f"a parameter set has {PARAMETER_COUNT} values, got shape {v.shape}")
        try:
            return cls(
                a_mm=v[:18].reshape(6, 3).tolist(),
                b_mm=v[18:36].reshape(6, 3).tolist(),
                l0_mm=v[L0_INDEX:].tolist(),
            )
        except ValidationError as err:
            raise ParameterValidationError(f"invalid parameter set: {err}") from None

    @classmethod
    def from_robot(cls, robot: Robot) -> ParameterSet:
        """The nominal set of a robot file."""
        return cls.from_vector(np.concatenate([robot.a.ravel(), robot.b.ravel(), robot.l0]))

    @classmethod
    def from_words(cls, words: Sequence[int]) -> ParameterSet:
        """From 84 registers (float32 ABCD); ParameterValidationError for anything that is not a sane set."""
        if len(words) != PARAMETER_REGISTERS:
            raise ParameterValidationError(f"expected {PARAMETER_REGISTERS} registers, got {len(words)}")
        try:
            values = floats_from_words(words)
        except ValueError as err:
            raise ParameterValidationError(str(err)) from None
        return cls.from_vector(values)

    def to_vector(self) -> np.ndarray:
        return np.concatenate([np.ravel(self.a_mm), np.ravel(self.b_mm), self.l0_mm]).astype(float)

    def to_words(self) -> list[int]:
        """84 registers: float32 ABCD (values rounded to float32)."""
        return words_from_floats(self.to_vector().tolist())

    def as_float32(self) -> ParameterSet:
        """The set the controller will actually hold (every value rounded to float32)."""
        return ParameterSet.from_words(self.to_words())

    def crc32(self) -> int:
        return crc32_of_words(self.to_words())

    def sha256(self) -> str:
        return hashlib.sha256(words_to_bytes(self.to_words())).hexdigest()


def _now() -> str:
    return datetime.now(UTC).isoformat(timespec="microseconds")


class WriteRecord(BaseModel):
    """One write request: what, where, when and how it ended."""

    function: Literal["write_register", "write_registers"]
    address: int
    count: int
    at: str
    ok: bool = False
    error: str | None = None


class UploadRecord(BaseModel):
    """Audit record of one parameter operation (upload, rollback or save)."""

    operation: Literal["upload", "rollback", "save"]
    endpoint: str
    device_id: int
    started_at: str
    finished_at: str | None = None
    outcome: Literal["pending", "committed", "rolled_back", "saved", "refused", "failed"] = "pending"
    error: str | None = None
    identity: dict[str, int] | None = None
    offsets_only: bool = False
    params_sha256: str | None = None
    params_crc32: str | None = None
    previous_live_sha256: str | None = None
    previous_live_crc32: str | None = None
    live_after_sha256: str | None = None
    staged_registers: int | None = None
    writes: list[WriteRecord] = Field(default_factory=list)
    staging_readback_match: bool | None = None
    live_readback_match: bool | None = None
    controller_status: str | None = None
    saved: bool = False
    saved_readback_match: bool | None = None


@dataclass(frozen=True)
class Identity:
    magic: int
    protocol_version: int
    firmware_version: int
    serial_number: int
    capabilities: Capability
    parameter_count: int

    @property
    def offsets_only(self) -> bool:
        return Capability.OFFSETS_ONLY in self.capabilities and Capability.FULL_GEOMETRY not in self.capabilities

    def as_dict(self) -> dict[str, int]:
        return {
            "magic": self.magic,
            "protocol_version": self.protocol_version,
            "firmware_version": self.firmware_version,
            "serial_number": self.serial_number,
            "capabilities": int(self.capabilities),
            "parameter_count": self.parameter_count,
        }


class ControllerParams:
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

    def __enter__(self) -> ControllerParams:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

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
            function="write_register" if single else "write_registers", address=address, count=len(values), at=_now()
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
            capabilities=Capability(words[CAPABILITIES_REG.address] & 0x000F),
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

    # ------------------------------------------------------------------ transactions

    def _begin(self, operation: Literal["upload", "rollback", "save"]) -> tuple[UploadRecord, Identity]:
        record = UploadRecord(operation=operation, endpoint=self.endpoint, device_id=self.device_id,
                              started_at=_now())
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
            record.previous_live_sha256 = hashlib.sha256(words_to_bytes(live)).hexdigest()
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
        record.finished_at = _now()
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

    def upload(self, params: ParameterSet | Sequence[float] | np.ndarray, *, save: bool = False) -> UploadRecord:
        """Write, verify and commit a parameter set (see the module docstring); save=True also saves it."""
        target = params if isinstance(params, ParameterSet) else ParameterSet.from_vector(params)
        target = target.as_float32()
        words = target.to_words()
        record, identity = self._begin("upload")
        record.params_sha256 = target.sha256()
        record.params_crc32 = f"{target.crc32():08x}"
        try:
            live = self.read_live()
            if identity.offsets_only:
                if not np.array_equal(live.to_vector()[:L0_INDEX], target.to_vector()[:L0_INDEX]):
                    raise CapabilityError("offsets-only controller: this set changes a/b joint coordinates; only "
                                          "the six leg offsets l0 can be written; nothing written")
                first = L0_INDEX * REGISTERS_PER_FLOAT
                blocks = [(first, words[first:first + L0_REGISTERS])]
            elif Capability.FULL_GEOMETRY in identity.capabilities:
                blocks = [(k, words[k:k + self.chunk_registers]) for k in range(0, PARAMETER_REGISTERS,
                                                                                 self.chunk_registers)]
            else:
                raise CapabilityError(f"controller capabilities {identity.capabilities!r} allow no parameter writes")
            if identity.offsets_only:
                blocks = [(off + k, blk[k:k + self.chunk_registers]) for off, blk in blocks
                          for k in range(0, len(blk), self.chunk_registers)]
            record.staged_registers = sum(len(b) for _, b in blocks)
            self._command(record, ParamCommand.OPEN_STAGING)
            for offset, block in blocks:
                self._write(record, STAGING_BANK.address + offset, block)
            self._write(record, STAGED_LENGTH_REG.address, [record.staged_registers, *split_u32(target.crc32())])
            staged = self._read_block(STAGING_BANK)
            record.staging_readback_match = staged == words
            if not record.staging_readback_match:
                bad = [k for k, (a, b) in enumerate(zip(staged, words, strict=True)) if a != b]
                raise ReadbackMismatch(f"staging read-back differs at registers {bad[:8]}; not committed")
            self._command(record, ParamCommand.COMMIT)
            live_after = self._read_block(LIVE_BANK)
            live_crc = join_u32(self._read_block(LIVE_CRC32_REG))
            record.live_after_sha256 = hashlib.sha256(words_to_bytes(live_after)).hexdigest()
            record.live_readback_match = live_after == words and live_crc == target.crc32()
            if not record.live_readback_match:
                raise ReadbackMismatch("live set read back after COMMIT differs from the uploaded set")
            if save:
                self._save_steps(record)
        except ParamsError as err:
            self._finish(record, err)
            raise
        self._finish(record, None, "committed")
        return record

    def _save_steps(self, record: UploadRecord) -> None:
        self._command(record, ParamCommand.SAVE)
        saved = self._read_block(SAVED_BANK)
        live = self._read_block(LIVE_BANK)
        record.saved_readback_match = saved == live
        if not record.saved_readback_match:
            raise ReadbackMismatch("non-volatile set read back after SAVE differs from the live set")
        record.saved = True

    def save(self) -> UploadRecord:
        """Copy the live set to non-volatile memory (controller DISABLED) and verify it."""
        record, _ = self._begin("save")
        try:
            self._save_steps(record)
        except ParamsError as err:
            self._finish(record, err)
            raise
        self._finish(record, None, "saved")
        return record

    def rollback(self) -> UploadRecord:
        """Swap live and backup (controller DISABLED): undoes the last commit."""
        record, _ = self._begin("rollback")
        try:
            backup = self._read_block(BACKUP_BANK)
            self._command(record, ParamCommand.ROLLBACK)
            live_after = self._read_block(LIVE_BANK)
            record.live_after_sha256 = hashlib.sha256(words_to_bytes(live_after)).hexdigest()
            record.params_sha256 = hashlib.sha256(words_to_bytes(backup)).hexdigest()
            record.params_crc32 = f"{crc32_of_words(backup):08x}"
            record.live_readback_match = live_after == backup
            if not record.live_readback_match:
                raise ReadbackMismatch("live set after ROLLBACK is not the former backup")
        except ParamsError as err:
            self._finish(record, err)
            raise
        self._finish(record, None, "rolled_back")
        return record
