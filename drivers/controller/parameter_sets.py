"""What the controller's parameter interface carries, validated at the edge: the geometry set, the compensation
block, the controller's identity, the audit record of every operation and the errors.

``ParameterSet`` is the 42-value geometry (docs/protocols.md); ``CompensationBlock`` the register-map 1.1 block of
reading scales, backlash, compliances, thermal coefficients and stroke tables (``hilcal.protocols.compensation``).
Both are pydantic models that refuse what a controller would refuse, so nothing unchecked reaches the wire.
"""

from __future__ import annotations

import hashlib
import math
from collections.abc import Sequence
from dataclasses import dataclass
from datetime import UTC, datetime
from typing import Annotated, Any, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator, model_validator

from hilcal.protocols.compensation import (
    LEG_FIELDS,
    MAX_TABLE_POINTS,
    MIN_TABLE_POINTS,
    NEEDS_FORCE,
    NEEDS_TEMPERATURE,
    block_from_words,
    block_violations,
    block_words,
    zero_block,
)
from hilcal.protocols.registers import (
    A_B_LIMIT_MM,
    L0_INDEX,
    L0_MAX_MM,
    L0_MIN_MM,
    PARAMETER_COUNT,
    PARAMETER_REGISTERS,
    Capability,
    ParamStatus,
    crc32_of_words,
    floats_from_words,
    words_from_floats,
    words_to_bytes,
)
from hilcal.robot import Robot

Vec3 = Annotated[list[float], Field(min_length=3, max_length=3)]
Floats6 = Annotated[list[float], Field(min_length=6, max_length=6)]


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


def now_utc() -> str:
    """An audit timestamp: UTC, microseconds."""
    return datetime.now(UTC).isoformat(timespec="microseconds")


class WriteRecord(BaseModel):
    """One write request: what, where, when and how it ended (``sdo_download``: a CANopen SDO write, its address
    index << 8 | sub-index and ``object`` naming it with its node)."""

    function: Literal["write_register", "write_registers", "sdo_download"]
    address: int
    count: int
    at: str
    ok: bool = False
    error: str | None = None
    object: str | None = None


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
    compensation_sha256: str | None = None
    compensation_crc32: str | None = None
    previous_compensation_sha256: str | None = None
    previous_compensation_crc32: str | None = None
    compensation_readback_match: bool | None = None
    staged_registers: int | None = None
    writes: list[WriteRecord] = Field(default_factory=list)
    staging_readback_match: bool | None = None
    live_readback_match: bool | None = None
    controller_status: str | None = None
    saved: bool = False
    saved_readback_match: bool | None = None
    device: str | None = None
    """The device an upload went to, independent of the port it was reached on (CANopen: 1018h's vendor, product
    and serial with the node id): where a rollback of a device without a backup bank finds its last upload."""
    previous_params: dict[str, Any] | None = None
    """A device without a backup bank: the geometry it held before (a rollback writes it back)."""
    previous_compensation: dict[str, Any] | None = None
    checksum_match: bool | None = None
    restore_writes: list[WriteRecord] = Field(default_factory=list)
    """After a failure: the writes that put the old values back."""
    restored_readback_match: bool | None = None


@dataclass(frozen=True)
class Identity:
    """Who the controller is. A CANopen controller has no magic or protocol version (0): its 1018h vendor id,
    product code and revision say who it is, and ``parameter_count`` counts the geometry values it holds."""

    magic: int
    protocol_version: int
    firmware_version: int
    serial_number: int
    capabilities: Capability
    parameter_count: int
    vendor_id: int | None = None
    product_code: int | None = None
    node_id: int | None = None

    @property
    def compensation(self) -> bool:
        """Register map 1.1: the controller takes a compensation block with the geometry."""
        return Capability.COMPENSATION in self.capabilities

    @property
    def offsets_only(self) -> bool:
        return Capability.OFFSETS_ONLY in self.capabilities and Capability.FULL_GEOMETRY not in self.capabilities

    def as_dict(self) -> dict[str, int]:
        out = {
            "magic": self.magic,
            "protocol_version": self.protocol_version,
            "firmware_version": self.firmware_version,
            "serial_number": self.serial_number,
            "capabilities": int(self.capabilities),
            "parameter_count": self.parameter_count,
        }
        out.update({k: v for k, v in (("vendor_id", self.vendor_id), ("product_code", self.product_code),
                                      ("node_id", self.node_id)) if v is not None})
        return out


class CompensationBlock(BaseModel):
    """The compensation block (hilcal.protocols.compensation): per leg a reading scale, backlash, two compliances,
    a thermal coefficient and a table over the stroke; every value within the controller's sanity bounds."""

    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)

    scale_ppm: Floats6
    backlash_mm: Floats6
    compliance_mm_per_kn: Floats6
    compliance_mm_per_kn_m: Floats6
    thermal_ppm_per_k: Floats6
    table_start_mm: Floats6
    table_end_mm: Floats6
    table_mm: Annotated[list[list[float]], Field(min_length=6, max_length=6)]
    reference_temperature_c: float = 20.0

    @model_validator(mode="after")
    def _sane(self) -> CompensationBlock:
        points = {len(row) for row in self.table_mm}
        if len(points) != 1:
            raise ValueError(f"every leg's table needs the same number of points, got {sorted(points)}")
        n = points.pop()
        if not (n == 0 or MIN_TABLE_POINTS <= n <= MAX_TABLE_POINTS):
            raise ValueError(f"a table has 0 or {MIN_TABLE_POINTS}..{MAX_TABLE_POINTS} points, got {n}")
        problems = block_violations(self.to_block())
        if problems:
            raise ValueError("; ".join(problems))
        return self

    @classmethod
    def zero(cls) -> CompensationBlock:
        """The block that corrects nothing."""
        return cls.from_block(zero_block())

    @classmethod
    def from_block(cls, block: dict[str, Any]) -> CompensationBlock:
        """From the protocol's dict (ParameterValidationError if it is not a sane block)."""
        try:
            return cls.model_validate({k: v for k, v in block.items() if k != "table_points"})
        except ValidationError as err:
            raise ParameterValidationError(f"invalid compensation block: {err}") from None

    @classmethod
    def from_words(cls, words: Sequence[int]) -> CompensationBlock:
        """From the block's registers (ParameterValidationError for anything that is not a sane block)."""
        try:
            block = block_from_words(words)
        except ValueError as err:
            raise ParameterValidationError(str(err)) from None
        return cls.from_block(block)

    def to_block(self) -> dict[str, Any]:
        """The protocol's dict (hilcal.protocols.compensation.Block)."""
        out: dict[str, Any] = self.model_dump()
        out["table_points"] = len(self.table_mm[0])
        return out

    def to_words(self) -> list[int]:
        return block_words(self.to_block())

    def as_float32(self) -> CompensationBlock:
        """The block the controller will actually hold (every value rounded to float32)."""
        return CompensationBlock.from_words(self.to_words())

    @property
    def is_zero(self) -> bool:
        return all(v == 0.0 for name in LEG_FIELDS for v in getattr(self, name)) and not any(
            v != 0.0 for row in self.table_mm for v in row)

    def needs(self) -> Capability:
        """The sensor readings its terms use (FORCE_READING, TEMPERATURE_READING)."""
        caps = Capability(0)
        if any(v != 0.0 for name in NEEDS_FORCE for v in getattr(self, name)):
            caps |= Capability.FORCE_READING
        if any(v != 0.0 for name in NEEDS_TEMPERATURE for v in getattr(self, name)):
            caps |= Capability.TEMPERATURE_READING
        return caps

    def crc32(self) -> int:
        return crc32_of_words(self.to_words())

    def sha256(self) -> str:
        return hashlib.sha256(words_to_bytes(self.to_words())).hexdigest()
