"""A controller's Modbus register map as a validated file (TOML): where the device keeps its identity, state, command
and status registers, geometry, checksums, compensation block and sensor readings, in which data types, word order and
scales, and which upload transaction it takes ("staged" or "direct").

The driver and the simulated controller both read the map (declarative, shared like the DBC) and each encodes
registers with its own code. Built-in maps are package data in ``hilcal/protocols/modbus_maps/``; ``hilcal-1.1`` is
hilcal's own register map and the default. The format, key by key: docs/modbus_maps.md.
"""

from __future__ import annotations

import tomllib
from dataclasses import dataclass
from functools import cache
from importlib import resources
from pathlib import Path
from typing import Annotated, Any, Literal

from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator

from hilcal.protocols.compensation import BLOCK_REGISTERS
from hilcal.protocols.compensation import FORMAT as COMPENSATION_FORMAT
from hilcal.protocols.controller_states import ControllerState
from hilcal.protocols.registers import MAX_READ_REGISTERS, MAX_WRITE_REGISTERS, N_LEGS, Capability, ParamStatus

MAP_FORMAT = 1
DEFAULT_MAP = "hilcal-1.1"
MAPS_FOLDER = "modbus_maps"

DataType = Literal["u16", "i16", "u32", "i32", "f32", "f64"]
WordOrder = Literal["ABCD", "CDAB", "BADC", "DCBA"]
TYPE_REGISTERS: dict[str, int] = {"u16": 1, "i16": 1, "u32": 2, "i32": 2, "f32": 2, "f64": 4}
INTEGER_RANGE: dict[str, tuple[int, int]] = {"u16": (0, 0xFFFF), "i16": (-0x8000, 0x7FFF),
                                             "u32": (0, 0xFFFF_FFFF), "i32": (-0x8000_0000, 0x7FFF_FFFF)}
Address = Annotated[int, Field(ge=0, le=0xFFFF)]
Word = Annotated[int, Field(ge=0, le=0xFFFF)]
StateValue = Annotated[int, Field(ge=0, le=0xFFFF_FFFF)]
StateValues = StateValue | list[StateValue]
PARTS = ("a", "b", "l0")
PART_START = {"a": 0, "b": 3 * N_LEGS, "l0": 6 * N_LEGS}
PART_VALUES = {"a": 3 * N_LEGS, "b": 3 * N_LEGS, "l0": N_LEGS}
BANKS = ("live", "staging", "backup", "saved")
STATE_KEYS = {s.name.lower(): s for s in ControllerState}
STATUS_KEYS = {s.name.lower(): s for s in ParamStatus}


class RegisterMapError(ValueError):
    """A map file that cannot be read or is not a valid register map (the message names every bad key)."""


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)


class RegisterField(_Strict):
    """One value in one register (16-bit types) or consecutive registers (32- and 64-bit types)."""

    address: Address
    type: DataType = "u16"
    word_order: WordOrder | None = Field(default=None, description="None: [device] word_order")
    expect: int | None = Field(default=None, description="identity only: the value a compatible device holds")

    @property
    def count(self) -> int:
        return TYPE_REGISTERS[self.type]

    @model_validator(mode="after")
    def _expect_fits(self) -> RegisterField:
        if self.expect is not None:
            if self.type not in INTEGER_RANGE:
                raise ValueError(f"expect needs an integer type, not {self.type}")
            lo, hi = INTEGER_RANGE[self.type]
            if not lo <= self.expect <= hi:
                raise ValueError(f"expect = {self.expect} does not fit a {self.type}")
        return self


class DeviceSection(_Strict):
    """The device and its transaction: "staged" (staging banks, commit) or "direct" (writes go live)."""

    name: str = Field(min_length=1, max_length=100)
    description: str = ""
    transaction: Literal["staged", "direct"]
    word_order: WordOrder = "ABCD"
    max_read_registers: int = Field(default=MAX_READ_REGISTERS, ge=1, le=MAX_READ_REGISTERS)
    max_write_registers: int = Field(default=MAX_WRITE_REGISTERS, ge=1, le=MAX_WRITE_REGISTERS)


class IdentitySection(_Strict):
    """Registers that identify the device; those with ``expect`` must hold that value (the identity check)."""

    magic: RegisterField | None = None
    protocol_version: RegisterField | None = None
    firmware_version: RegisterField | None = None
    serial_number: RegisterField | None = None
    capabilities: RegisterField | None = None
    parameter_count: RegisterField | None = None

    def fields(self) -> dict[str, RegisterField]:
        return {k: v for k, v in self if v is not None}


class StateSection(_Strict):
    """The state register: (raw value & mask) names a ControllerState; only ``disabled`` is required."""

    address: Address
    type: Literal["u16", "i16", "u32", "i32"] = "u16"
    word_order: WordOrder | None = None
    mask: int = Field(default=0xFFFF, ge=1, le=0xFFFF_FFFF)
    disabled: StateValues
    enabled: StateValues | None = None
    moving: StateValues | None = None
    in_position: StateValues | None = None
    fault: StateValues | None = None
    estop: StateValues | None = None

    @property
    def count(self) -> int:
        return TYPE_REGISTERS[self.type]

    def values(self) -> dict[ControllerState, tuple[int, ...]]:
        """Each mapped state's raw values (after the mask)."""
        out = {}
        for key, state in STATE_KEYS.items():
            value = getattr(self, key)
            if value is not None:
                out[state] = tuple(value) if isinstance(value, list) else (value,)
        return out

    @model_validator(mode="after")
    def _distinct(self) -> StateSection:
        seen: dict[int, str] = {}
        for state, values in self.values().items():
            for v in values:
                if v & self.mask != v:
                    raise ValueError(f"{state.name.lower()} = 0x{v:X} has bits outside mask 0x{self.mask:X}")
                if v in seen:
                    raise ValueError(f"{state.name.lower()} and {seen[v]} share the value 0x{v:X}")
                seen[v] = state.name.lower()
        return self


class CommandsSection(_Strict):
    """The command register (a u16 written with FC 6) and the code of each command the device has."""

    address: Address
    open_staging: Word | None = None
    commit: Word | None = None
    rollback: Word | None = None
    save: Word | None = None

    @property
    def count(self) -> int:
        return 1

    def codes(self) -> dict[str, int]:
        return {k: v for k, v in self if k != "address" and v is not None}

    @model_validator(mode="after")
    def _distinct(self) -> CommandsSection:
        codes = self.codes()
        if len(set(codes.values())) != len(codes):
            raise ValueError(f"two commands share a code: {codes}")
        return self


class StatusSection(_Strict):
    """The register holding the outcome of the last command (u16), and its values (hilcal's ParamStatus names)."""

    address: Address
    ok: Word = 0
    not_disabled: Word | None = None
    incomplete_staging: Word | None = None
    length_mismatch: Word | None = None
    crc_mismatch: Word | None = None
    not_finite: Word | None = None
    limit_violation: Word | None = None
    capability_violation: Word | None = None
    no_backup: Word | None = None
    not_supported: Word | None = None
    no_command: Word | None = None

    @property
    def count(self) -> int:
        return 1

    def codes(self) -> dict[ParamStatus, int]:
        return {STATUS_KEYS[k]: v for k, v in self if k != "address" and v is not None}

    @model_validator(mode="after")
    def _distinct(self) -> StatusSection:
        codes = self.codes()
        if len(set(codes.values())) != len(codes):
            raise ValueError("two statuses share a value")
        return self


class GeometryPart(_Strict):
    """Where one part of the geometry (a: 18 values, b: 18, l0: 6) starts in each bank; its encoding, if not the
    [geometry] defaults."""

    live: Address
    staging: Address | None = None
    backup: Address | None = None
    saved: Address | None = None
    type: DataType | None = None
    word_order: WordOrder | None = None
    scale: float | None = Field(default=None, description="mm per count")
    offset: float | None = Field(default=None, description="mm at count 0")


class GeometrySection(_Strict):
    """The parts the device holds (l0 alone, or a, b and l0) and the default encoding: mm = count * scale + offset."""

    type: DataType = "f32"
    word_order: WordOrder | None = None
    scale: float = 1.0
    offset: float = 0.0
    a: GeometryPart | None = None
    b: GeometryPart | None = None
    l0: GeometryPart


class ChecksumSection(_Strict):
    """u32 registers holding the CRC-32 of a bank (``staged``: written by the host before commit)."""

    live: Address | None = None
    backup: Address | None = None
    saved: Address | None = None
    staged: Address | None = None


class StagingSection(_Strict):
    """Staged transaction extras: ``length``, a u16 the host writes with the number of staging registers it wrote."""

    length: Address | None = None


class CompensationSection(_Strict):
    """hilcal's compensation block (docs/protocols.md, format 1): the first register of each bank."""

    format: Literal[1] = COMPENSATION_FORMAT
    live: Address
    staging: Address | None = None
    backup: Address | None = None
    saved: Address | None = None
    checksum: ChecksumSection | None = None


class SensorsSection(_Strict):
    """The controller's own readings: six leg forces (kN) and the leg temperature (°C), each of its type."""

    leg_forces_kn: RegisterField | None = None
    temperature_c: RegisterField | None = None


@dataclass(frozen=True)
class PartLayout:
    """One geometry part resolved: its slice of the 42-value set, encoding and bank addresses."""

    name: str
    start: int
    values: int
    type: str
    word_order: str
    scale: float
    offset: float
    banks: dict[str, int | None]

    @property
    def registers(self) -> int:
        return self.values * TYPE_REGISTERS[self.type]


class RegisterMap(_Strict):
    """A whole map file (see the module docstring)."""

    format: Literal[1]
    device: DeviceSection
    identity: IdentitySection | None = None
    state: StateSection | None = None
    fault_code: RegisterField | None = None
    commands: CommandsSection | None = None
    status: StatusSection | None = None
    diagnostics: dict[str, RegisterField] = Field(default_factory=dict)
    geometry: GeometrySection
    checksum: ChecksumSection | None = None
    staging: StagingSection | None = None
    compensation: CompensationSection | None = None
    sensors: SensorsSection | None = None

    @property
    def staged(self) -> bool:
        return self.device.transaction == "staged"

    def word_order(self, own: str | None) -> str:
        return own or self.device.word_order

    def parts(self) -> tuple[PartLayout, ...]:
        """The geometry parts the device holds, in set order (a, b, l0)."""
        g = self.geometry
        out = []
        for name in PARTS:
            part: GeometryPart | None = getattr(g, name)
            if part is None:
                continue
            out.append(PartLayout(
                name, PART_START[name], PART_VALUES[name], part.type or g.type,
                self.word_order(part.word_order or g.word_order), g.scale if part.scale is None else part.scale,
                g.offset if part.offset is None else part.offset, {b: getattr(part, b) for b in BANKS}))
        return tuple(out)

    def held_values(self) -> int:
        """How many of the 42 values the device holds (42, or 6 for the leg offsets alone)."""
        return sum(p.values for p in self.parts())

    def capabilities(self) -> Capability:
        """What the map lets the driver do with a device; a CAPABILITIES register may narrow it."""
        caps = Capability.FULL_GEOMETRY | Capability.OFFSETS_ONLY if self.geometry.a else Capability.OFFSETS_ONLY
        codes = self.commands.codes() if self.commands else {}
        if "save" in codes:
            caps |= Capability.NONVOLATILE_SAVE
        if "rollback" in codes or (not self.staged and self.geometry.l0.backup is not None):
            caps |= Capability.ROLLBACK
        if self.compensation is not None:
            caps |= Capability.COMPENSATION
        if self.sensors is not None and self.sensors.leg_forces_kn is not None:
            caps |= Capability.FORCE_READING
        if self.sensors is not None and self.sensors.temperature_c is not None:
            caps |= Capability.TEMPERATURE_READING
        return caps

    def spans(self) -> list[tuple[str, int, int]]:
        """(key, first address, register count) of every register the map names."""
        out: list[tuple[str, int, int]] = []
        for key, f in (self.identity.fields() if self.identity else {}).items():
            out.append((f"identity.{key}", f.address, f.count))
        for key in ("state", "fault_code", "commands", "status"):
            f = getattr(self, key)
            if f is not None:
                out.append((key, f.address, f.count))
        out += [(f"diagnostics.{k}", f.address, f.count) for k, f in self.diagnostics.items()]
        for prefix, section in (("checksum", self.checksum),
                                ("compensation.checksum", self.compensation and self.compensation.checksum)):
            out += [(f"{prefix}.{k}", v, 2) for k, v in (section or ChecksumSection()) if v is not None]
        if self.staging and self.staging.length is not None:
            out.append(("staging.length", self.staging.length, 1))
        for part in self.parts():
            out += [(f"geometry.{part.name}.{b}", a, part.registers) for b, a in part.banks.items() if a is not None]
        if self.compensation is not None:
            out += [(f"compensation.{b}", getattr(self.compensation, b), BLOCK_REGISTERS) for b in BANKS
                    if getattr(self.compensation, b) is not None]
        if self.sensors is not None:
            if self.sensors.leg_forces_kn is not None:
                f = self.sensors.leg_forces_kn
                out.append(("sensors.leg_forces_kn", f.address, N_LEGS * f.count))
            if self.sensors.temperature_c is not None:
                f = self.sensors.temperature_c
                out.append(("sensors.temperature_c", f.address, f.count))
        return out

    @model_validator(mode="after")
    def _consistent(self) -> RegisterMap:
        problems = _step_problems(self) + _geometry_problems(self) + _span_problems(self.spans())
        if problems:
            raise ValueError("; ".join(problems))
        return self


def _step_problems(m: RegisterMap) -> list[str]:
    """The transaction's steps against the registers they need."""
    codes = m.commands.codes() if m.commands else {}
    problems = []
    if m.staged:
        for step in ("open_staging", "commit"):
            if step not in codes:
                problems.append(f"commands.{step}: transaction = \"staged\" needs the {step} command code "
                                "(and a [commands] register)")
        if m.status is None:
            problems.append("status: transaction = \"staged\" needs a [status] register (the outcome of each command)")
    else:
        problems += [f"commands.{step}: transaction = \"direct\" has no {step} step (staged only)"
                     for step in ("open_staging", "commit", "rollback") if step in codes]
        if m.checksum is not None and m.checksum.staged is not None:
            problems.append("checksum.staged: a staged checksum needs transaction = \"staged\"")
        if m.compensation and m.compensation.checksum and m.compensation.checksum.staged is not None:
            problems.append("compensation.checksum.staged: a staged checksum needs transaction = \"staged\"")
        if m.staging is not None:
            problems.append("staging: a [staging] section needs transaction = \"staged\"")
    if "rollback" in codes and m.status is None:
        problems.append("status: the rollback command needs a [status] register")
    return problems


def _geometry_problems(m: RegisterMap) -> list[str]:
    g = m.geometry
    problems = []
    if (g.a is None) != (g.b is None):
        problems.append("geometry: a device holds a and b together (with l0), or l0 alone")
    codes = m.commands.codes() if m.commands else {}
    for part in m.parts():
        key = f"geometry.{part.name}"
        if part.scale == 0.0:
            problems.append(f"{key}.scale: must not be 0")
        if m.staged and part.banks["staging"] is None:
            problems.append(f"{key}.staging: transaction = \"staged\" needs the part's staging address")
        if not m.staged and part.banks["staging"] is not None:
            problems.append(f"{key}.staging: a staging bank needs transaction = \"staged\"")
        if "rollback" in codes and part.banks["backup"] is None:
            problems.append(f"{key}.backup: the rollback command needs the part's backup address")
        if m.staged is False and (part.banks["backup"] is None) != (g.l0.backup is None):
            problems.append(f"{key}.backup: give backup addresses for every part or for none")
    c = m.compensation
    if c is not None:
        if m.staged and c.staging is None:
            problems.append("compensation.staging: transaction = \"staged\" needs the block's staging address")
        if not m.staged and c.staging is not None:
            problems.append("compensation.staging: a staging bank needs transaction = \"staged\"")
        if "rollback" in codes and c.backup is None:
            problems.append("compensation.backup: the rollback command needs the block's backup address")
    return problems


def _span_problems(spans: list[tuple[str, int, int]]) -> list[str]:
    problems = [f"{key}: 0x{start:04X} + {count} registers runs past 0xFFFF" for key, start, count in spans
                if start + count > 0x10000]
    reach: tuple[str, int, int] | None = None
    for key, start, count in sorted(spans, key=lambda s: (s[1], s[0])):
        if reach is not None and start < reach[1] + reach[2]:
            k, s, n = reach
            problems.append(f"{key} (0x{start:04X}..0x{start + count - 1:04X}) overlaps {k} "
                            f"(0x{s:04X}..0x{s + n - 1:04X})")
        if reach is None or start + count > reach[1] + reach[2]:
            reach = (key, start, count)
    return problems


def _format_errors(err: ValidationError, source: str) -> str:
    lines = [f"{source}: {err.error_count()} problem(s)"]
    for e in err.errors():
        where = ".".join(str(p) for p in e["loc"])
        message = e["msg"].removeprefix("Value error, ")
        lines.append(f"  {where}: {message}" if where else f"  {message}")
    return "\n".join(lines)


def register_map_from_dict(data: dict[str, Any], source: str = "<register map>") -> RegisterMap:
    """Validate a parsed map; RegisterMapError naming every bad key."""
    try:
        return RegisterMap.model_validate(data)
    except ValidationError as err:
        raise RegisterMapError(_format_errors(err, source)) from None


def built_in_maps() -> list[str]:
    """Names of the maps shipped with hilcal (``hilcal/protocols/modbus_maps/NAME.toml``)."""
    folder = resources.files(__package__).joinpath(MAPS_FOLDER)
    return sorted(p.name.removesuffix(".toml") for p in folder.iterdir() if p.name.endswith(".toml"))


def register_map_text(source: str | Path) -> tuple[str, str]:
    """(text, where) of a built-in map's name or a map file's path; RegisterMapError if it cannot be read."""
    if isinstance(source, str) and source in built_in_maps():
        path = resources.files(__package__).joinpath(MAPS_FOLDER, f"{source}.toml")
        return path.read_text(encoding="utf-8"), f"built-in register map {source}"
    p = Path(source)
    try:
        return p.read_text(encoding="utf-8"), f"register map {p}"
    except OSError as err:
        names = ", ".join(built_in_maps())
        raise RegisterMapError(f"register map {source}: neither a built-in map ({names}) nor a readable file: "
                               f"{err.strerror or err}") from None


def load_register_map(source: str | Path) -> RegisterMap:
    """A built-in map by name (``hilcal-1.1``) or a map file by path, validated; RegisterMapError otherwise."""
    if isinstance(source, str) and source == DEFAULT_MAP:
        return default_register_map()
    text, where = register_map_text(source)
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as err:
        raise RegisterMapError(f"{where}: not valid TOML: {err}") from None
    return register_map_from_dict(data, where)


@cache
def default_register_map() -> RegisterMap:
    """hilcal's own register map 1.1 (``modbus_maps/hilcal-1.1.toml``), read once."""
    text, where = register_map_text(DEFAULT_MAP)
    return register_map_from_dict(tomllib.loads(text), where)
