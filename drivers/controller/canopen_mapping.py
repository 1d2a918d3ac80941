"""Where a CANopen controller keeps each thing hilcal needs, as data (a station's ``[controller]`` keys), checked
against the device's EDS/DCF before anything is sent.

An object reference is ``"0x6064"`` (sub-index 0), ``"0x2010:3"`` or, on a bus of several nodes, ``"0x607C:0@4"``
(node 4; without ``@`` the first node). A group of values is a list of references, or a table: ``{ array = "0x2010",
first = 1 }`` (consecutive sub-indices of one object), ``{ records = ["0x2101", ...], subs = [1, 2, 3] }`` (one
object per leg, x, y, z at those sub-indices), ``{ per_node = "0x607A" }`` (the same object on each leg's node).
Lengths on the wire are ``mm * scale`` (REAL32: scale 1 for mm; INTEGER32 in µm: scale 1000); an integer object needs
its scale said. Device control is CiA 402's (CiA 402-2 §8.4: controlword 6040h, statusword 6041h and its state
coding) unless the mapping says otherwise; store and restore are CiA 301's 1010h "save" and 1011h "load" (CiA 301
v4.2.0 §7.5.2.13-14). ``resolve`` checks every reference: the object exists, it is a number, it can be read (and
written where hilcal writes it); a ``MappingError`` names the key.
"""

from __future__ import annotations

import re
import struct
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Literal

from canopen.objectdictionary import ObjectDictionary, ODArray, ODRecord, ODVariable, datatypes
from pydantic import BaseModel, ConfigDict, Field, field_validator, model_validator

from hilcal.protocols.compensation import LEG_FIELDS

N_LEGS = 6
SAVE_SIGNATURE = 0x65766173
"""``"save"`` read as a little-endian UNSIGNED32 (CiA 301 v4.2.0 §7.5.2.13)."""
LOAD_SIGNATURE = 0x64616F6C
"""``"load"`` read as a little-endian UNSIGNED32 (CiA 301 v4.2.0 §7.5.2.14)."""
_REF = re.compile(r"^\s*(0x[0-9A-Fa-f]{1,4}|\d{1,5})(?::(0x[0-9A-Fa-f]{1,2}|\d{1,3}))?(?:@(\d{1,3}))?\s*$")
TYPE_NAMES = {v: k for k, v in vars(datatypes).items() if k.isupper() and isinstance(v, int)}


class MappingError(ValueError):
    """A mapping that does not fit the device (or is not a mapping): the message names the key."""


@dataclass(frozen=True)
class ObjectRef:
    """One object of a node's dictionary; ``node`` None: the controller's first node."""

    index: int
    subindex: int = 0
    node: int | None = None

    @classmethod
    def parse(cls, text: str) -> ObjectRef:
        m = _REF.match(text) if isinstance(text, str) else None
        if m is None:
            raise ValueError(f"{text!r} is not an object reference (0xIIII, 0xIIII:S or 0xIIII:S@NODE)")
        index, sub, node = int(m[1], 0), int(m[2], 0) if m[2] else 0, int(m[3]) if m[3] else None
        if not (0 < index <= 0xFFFF and 0 <= sub <= 0xFF and (node is None or 1 <= node <= 127)):
            raise ValueError(f"{text!r}: index 0x0001-0xFFFF, sub-index 0-255, node 1-127")
        return cls(index, sub, node)

    def on(self, node: int) -> ObjectRef:
        return ObjectRef(self.index, self.subindex, node)

    def __str__(self) -> str:
        return f"0x{self.index:04X}:{self.subindex}" + ("" if self.node is None else f"@{self.node}")


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)


def _ref(value: str) -> str:
    ObjectRef.parse(value)
    return value


def _none_word(value: object) -> object:
    """TOML has no null: ``"none"`` says the device lacks a bit or a command whose default is CiA 402's."""
    return None if isinstance(value, str) and value.strip().lower() == "none" else value


class ObjectsTable(_Strict):
    """A group of objects written as a table (see the module docstring); exactly one of its forms."""

    array: str | None = Field(default=None, description="one object: its sub-indices first, first + 1, ...")
    first: int = Field(default=1, ge=0, le=255)
    records: list[str] | None = Field(default=None, description="one object per leg, its values at `subs`")
    subs: list[int] = Field(default_factory=lambda: [1, 2, 3])
    per_node: str | None = Field(default=None, description="the same object on each leg's node")

    @model_validator(mode="after")
    def _one_form(self) -> ObjectsTable:
        forms = [f for f in ("array", "records", "per_node") if getattr(self, f) is not None]
        if len(forms) != 1:
            raise ValueError("a table of objects has exactly one of array, records, per_node")
        for ref in [self.array, self.per_node, *(self.records or [])]:
            if ref is not None:
                _ref(ref)
        return self


Objects = list[str] | ObjectsTable


def expand(objects: Objects, count: int, key: str, leg_nodes: Sequence[int]) -> list[ObjectRef]:
    """The ``count`` references of a group; MappingError naming ``key`` for a wrong count."""
    if isinstance(objects, list):
        refs = [ObjectRef.parse(r) for r in objects]
    elif objects.array is not None:
        base = ObjectRef.parse(objects.array)
        refs = [ObjectRef(base.index, objects.first + k, base.node) for k in range(count)]
        if objects.first + count - 1 > 255:
            raise MappingError(f"{key}: {count} sub-indices from {objects.first} pass 255")
    elif objects.records is not None:
        refs = [ObjectRef(base.index, sub, base.node) for base in map(ObjectRef.parse, objects.records)
                for sub in objects.subs]
    else:
        base = ObjectRef.parse(objects.per_node or "")
        per = count // N_LEGS if count % N_LEGS == 0 else 0
        if len(leg_nodes) != N_LEGS or per != 1:
            raise MappingError(f"{key}: per_node needs one node per leg ({N_LEGS} nodes) and one value per leg")
        refs = [base.on(node) for node in leg_nodes]
    if len(refs) != count:
        raise MappingError(f"{key}: {count} objects expected, the mapping gives {len(refs)}")
    return refs


POWER_STATES = ("not_ready", "switch_on_disabled", "ready", "switched_on", "enabled", "quick_stop", "fault_reaction",
                "fault")
"""CiA 402-2 §8.4's states, the names a statusword coding may give."""


class DeviceControl(_Strict):
    """Controlword values and statusword coding; CiA 402-2 §8.4 (tables 'command coding' and 'state coding')."""

    controlword: str = "0x6040"
    statusword: str = "0x6041"
    nodes: list[int] | None = Field(default=None, description="nodes that each have this device control "
                                    "(default: every node of the controller)")
    shutdown: int = 0x0006
    switch_on: int = 0x0007
    enable_operation: int = 0x000F
    disable_voltage: int = 0x0000
    quick_stop: int | None = Field(default=0x0002, ge=0, le=0xFFFF, description="quick stop (e-stop); "
                                   '"none": no stop over the bus, only the hardware e-stop')
    fault_reset: int = 0x0080
    halt_bit: int | None = Field(default=8, ge=0, le=15, description="controlword bit that halts a move (stop); "
                                 '"none": a move runs to its end')
    power_states: bool = Field(default=True, description="false: the device has no CiA 402 power state machine; it "
                               "follows setpoints whenever its statusword does not code `fault`, and is at rest (takes "
                               "parameters) when target_reached_bit is set; enable and disable write nothing")
    states: dict[str, tuple[int, int]] = Field(default_factory=lambda: {
        "not_ready": (0x004F, 0x0000), "switch_on_disabled": (0x004F, 0x0040), "ready": (0x006F, 0x0021),
        "switched_on": (0x006F, 0x0023), "enabled": (0x006F, 0x0027), "quick_stop": (0x006F, 0x0007),
        "fault_reaction": (0x004F, 0x000F), "fault": (0x004F, 0x0008)},
        description="state -> (mask, value) of the statusword")
    operation_mode: int | None = Field(default=None, ge=-128, le=127, description="written to mode_object before "
                                       "enabling, read back from mode_display (CiA 402 profile position: 1)")
    mode_object: str = "0x6060"
    mode_display: str = "0x6061"
    target_reached_bit: int = Field(default=10, ge=0, le=15)
    limit_bit: int | None = Field(default=11, ge=0, le=15, description='internal limit active; "none": not shown')

    @field_validator("controlword", "statusword", "mode_object", "mode_display")
    @classmethod
    def _refs(cls, v: str) -> str:
        return _ref(v)

    @field_validator("quick_stop", "halt_bit", "limit_bit", mode="before")
    @classmethod
    def _absent(cls, v: object) -> object:
        return _none_word(v)

    @model_validator(mode="after")
    def _all_states(self) -> DeviceControl:
        unknown = set(self.states) - set(POWER_STATES)
        if unknown:
            raise ValueError(f"unknown statusword state(s) {sorted(unknown)}; the states are {', '.join(POWER_STATES)}")
        needed = {"switch_on_disabled", "ready", "switched_on", "enabled", "fault"} if self.power_states else {"fault"}
        missing = needed - set(self.states)
        if missing:
            raise ValueError(f"the statusword coding lacks {sorted(missing)}")
        if not self.power_states and set(self.states) != {"fault"}:
            raise ValueError("a device without power states (power_states = false) codes `fault` only: it is at rest "
                             "when target_reached_bit is set and moving otherwise")
        return self


class Setpoints(_Strict):
    """The legs' setpoints, written by SDO, and, where the device needs it, how a new set is applied: an object
    written after the six (``apply``, with a rolling tag when ``apply_counter``; ``apply_result`` read after it, 0 =
    accepted) or the CiA 402 profile-position handshake (``new_setpoint_bit`` raised, ``ack_bit`` acknowledges)."""

    legs: Objects
    scale: float | None = Field(default=None, gt=0, description="device units per mm (REAL in mm: 1)")
    apply: str | None = Field(default=None, description="object written after the six to apply them")
    apply_value: int = Field(default=1, ge=0, description="the value written to `apply` (without apply_counter)")
    apply_counter: bool = Field(default=False, description="write 1, 2, 3, ... to `apply` (a tag of the set)")
    apply_result: str | None = Field(default=None, description="object read after `apply`: 0 accepted")
    apply_results: dict[int, str] = Field(default_factory=dict, description="apply_result value -> its meaning")
    new_setpoint_bit: int | None = Field(default=None, ge=0, le=15, description="controlword bit raised to apply "
                                         "(CiA 402 profile position: 4)")
    change_immediately_bit: int | None = Field(default=None, ge=0, le=15, description="CiA 402 pp: 5")
    ack_bit: int | None = Field(default=None, ge=0, le=15, description="statusword bit acknowledging a new "
                                "setpoint (CiA 402 pp: 12)")

    @field_validator("apply", "apply_result")
    @classmethod
    def _apply(cls, v: str | None) -> str | None:
        return None if v is None else _ref(v)


class Actual(_Strict):
    """The legs' measured lengths: six objects, read by SDO."""

    legs: Objects
    scale: float | None = Field(default=None, gt=0, description="device units per mm (REAL in mm: 1)")


class Geometry(_Strict):
    """Where the geometry lives; any part may be left out (many devices hold only the leg offsets l0): a part left
    out is the robot file's and cannot be uploaded."""

    a_mm: Objects | None = None
    b_mm: Objects | None = None
    l0_mm: Objects | None = None
    scale: float | None = Field(default=None, gt=0, description="device units per mm (REAL in mm: 1)")


class Compensation(_Strict):
    """The compensation block's terms the device holds (hilcal.protocols.compensation), six objects each; a term left
    out is zero on the device and an upload that needs it is refused."""

    scale_ppm: Objects | None = None
    backlash_mm: Objects | None = None
    compliance_mm_per_kn: Objects | None = None
    compliance_mm_per_kn_m: Objects | None = None
    thermal_ppm_per_k: Objects | None = None
    table_start_mm: Objects | None = None
    table_end_mm: Objects | None = None
    reference_temperature_c: str | None = None
    table_mm: list[str] | None = Field(default=None, description="six DOMAIN objects, each a leg's stroke table "
                                       "as REAL32 values (little-endian)")
    table_points: str | None = Field(default=None, description="the object that says how many points a table "
                                     "has (written before the tables)")
    scales: dict[str, float] = Field(default_factory=dict, description="term -> device units per term unit")

    @field_validator("scales")
    @classmethod
    def _known(cls, v: dict[str, float]) -> dict[str, float]:
        unknown = set(v) - {*LEG_FIELDS, "reference_temperature_c", "table_mm"}
        if unknown:
            raise ValueError(f"no compensation term {sorted(unknown)}")
        if any(not s > 0 for s in v.values()):
            raise ValueError("a scale is positive")
        return v


class Readings(_Strict):
    """The sensor readings the compensation uses, where the device has them."""

    forces_kn: Objects | None = None
    temperature_c: str | None = None
    force_scale: float = Field(default=1.0, gt=0)
    temperature_scale: float = Field(default=1.0, gt=0)


class Checksum(_Strict):
    """An object holding the device's checksum of its parameter set, compared after every write."""

    object: str
    algorithm: Literal["crc32-float32-be", "crc32-objects"] = Field(
        default="crc32-objects", description="crc32-float32-be: CRC-32 of the 42 values as float32 big-endian in "
        "a, b, l0 order (hilcal's register layout); crc32-objects: CRC-32 of the mapped geometry objects' bytes as "
        "on the wire (little-endian, their EDS types) in a, b, l0 order")


class Command(_Strict):
    """A CiA 301 command object: writing ``signature`` to ``object``."""

    object: str
    signature: int = Field(ge=0, le=0xFFFFFFFF)


class IdentityCheck(_Strict):
    """What 1018h must say (nothing: any device is taken)."""

    vendor_id: int | None = Field(default=None, ge=0, le=0xFFFFFFFF)
    product_code: int | None = Field(default=None, ge=0, le=0xFFFFFFFF)
    min_revision: int | None = Field(default=None, ge=0, le=0xFFFFFFFF)


class CanopenMapping(_Strict):
    """Everything the driver reads and writes, by object (see the module docstring)."""

    device_control: DeviceControl = Field(default_factory=DeviceControl)
    setpoints: Setpoints
    actual: Actual
    geometry: Geometry = Field(default_factory=Geometry)
    compensation: Compensation = Field(default_factory=Compensation)
    readings: Readings = Field(default_factory=Readings)
    checksum: Checksum | None = None
    store: Command | None = Field(default_factory=lambda: Command(object="0x1010:1", signature=SAVE_SIGNATURE))
    restore: Command | None = Field(default_factory=lambda: Command(object="0x1011:1", signature=LOAD_SIGNATURE))
    identity: IdentityCheck = Field(default_factory=IdentityCheck)
    emcy_codes: dict[str, str] = Field(default_factory=dict, description="vendor emergency codes -> names")

    @field_validator("emcy_codes")
    @classmethod
    def _codes(cls, v: dict[str, str]) -> dict[str, str]:
        for code in v:
            try:
                ok = 0 <= int(code, 0) <= 0xFFFF
            except ValueError:
                ok = False
            if not ok:
                raise ValueError(f"emergency code {code!r}: 0x0000-0xFFFF")
        return v

    def vendor_codes(self) -> dict[int, str]:
        return {int(k, 0): v for k, v in self.emcy_codes.items()}


@dataclass(frozen=True, eq=False)
class Slot:
    """One resolved numeric object: where it is, its type, and how a value in the group's unit becomes its raw."""

    key: str
    ref: ObjectRef
    node: int
    variable: ODVariable
    scale: float

    @property
    def is_float(self) -> bool:
        return self.variable.data_type in datatypes.FLOAT_TYPES

    def raw(self, value: float) -> int | float:
        """The raw value for ``value`` (group units): float32/64 rounding on the wire, or rounded to an integer;
        ValueError if it does not fit the type."""
        scaled = value * self.scale
        if self.is_float:
            return self.variable.decode_raw(self.variable.encode_raw(float(scaled)))
        raw = round(scaled)
        lo, hi = _int_range(self.variable.data_type)
        if not lo <= raw <= hi:
            kind = TYPE_NAMES.get(self.variable.data_type)
            raise ValueError(f"{self.key} ({self.ref}): {value} needs {raw}, outside {kind} [{lo}, {hi}]")
        return raw

    def value(self, raw: int | float) -> float:
        return float(raw) / self.scale

    def encode(self, raw: int | float) -> bytes:
        return self.variable.encode_raw(raw)

    def decode(self, data: bytes) -> int | float:
        return self.variable.decode_raw(data)

    def __str__(self) -> str:
        return f"{self.key} {self.ref.on(self.node)} ({self.variable.qualname})"


@dataclass(frozen=True, eq=False)
class TableSlot(Slot):
    """A DOMAIN object holding a table as REAL32 values, little-endian; its raw value is the bytes."""

    @property
    def is_float(self) -> bool:
        return False

    def raw(self, value: Sequence[float]) -> bytes:  # type: ignore[override]
        return struct.pack(f"<{len(value)}f", *(float(v) * self.scale for v in value))

    def value(self, raw: bytes) -> list[float]:  # type: ignore[override]
        return [v / self.scale for v in struct.unpack(f"<{len(raw) // 4}f", raw[: len(raw) // 4 * 4])]

    def encode(self, raw: bytes) -> bytes:  # type: ignore[override]
        return bytes(raw)

    def decode(self, data: bytes) -> bytes:  # type: ignore[override]
        return bytes(data)


def drive_state(word: int, control: DeviceControl) -> str:
    """The device-control state a statusword codes (the mapping's coding, CiA 402's by default); "unknown". A device
    without power states (``power_states = false``) is "fault", "at_rest" (target reached) or "moving"."""
    for name, (mask, value) in control.states.items():
        if word & mask == value:
            return name
    if not control.power_states:
        return "at_rest" if word >> control.target_reached_bit & 1 else "moving"
    return "unknown"


def _int_range(data_type: int | None) -> tuple[int, int]:
    bits = ODVariable.STRUCT_TYPES[data_type].size * 8 if data_type in ODVariable.STRUCT_TYPES else 32
    if hasattr(ODVariable.STRUCT_TYPES.get(data_type), "bits"):
        bits = ODVariable.STRUCT_TYPES[data_type].bits  # IntegerN / UnsignedN
    if data_type in datatypes.SIGNED_TYPES:
        return -(1 << (bits - 1)), (1 << (bits - 1)) - 1
    return 0, (1 << bits) - 1


def lookup(dictionaries: Mapping[int, ObjectDictionary], ref: ObjectRef, default_node: int, key: str,
           source: str) -> tuple[int, ODVariable]:
    """The (node, variable) of a reference; MappingError naming the key and what the EDS holds instead."""
    node = default_node if ref.node is None else ref.node
    od = dictionaries.get(node)
    if od is None:
        raise MappingError(f"{key}: {ref} is on node {node}, which this controller does not have "
                           f"(nodes {sorted(dictionaries)})")
    if ref.index not in od:
        raise MappingError(f"{key}: object 0x{ref.index:04X} does not exist in {source}")
    obj = od[ref.index]
    if isinstance(obj, ODVariable):
        if ref.subindex != 0:
            raise MappingError(f"{key}: 0x{ref.index:04X} ({obj.name}) is a single variable in {source}: "
                               f"sub-index {ref.subindex} does not exist")
        return node, obj
    assert isinstance(obj, ODRecord | ODArray)
    if ref.subindex not in obj or (isinstance(obj, ODArray) and ref.subindex > _array_length(obj)):
        subs = sorted(obj) if isinstance(obj, ODRecord) else f"0..{_array_length(obj)}"
        raise MappingError(f"{key}: {ref} does not exist in {source}: 0x{ref.index:04X} ({obj.name}) has "
                           f"sub-indices {subs}")
    return node, obj[ref.subindex]


def _array_length(array: ODArray) -> int:
    sub0 = array[0]
    length = sub0.default if isinstance(sub0.default, int) else None
    return length if length is not None else max(array.subindices, default=0)


def numeric(node: int, variable: ODVariable, ref: ObjectRef, key: str, source: str, *, write: bool,
            scale: float | None, unit_scale_needed: bool = True) -> Slot:
    """A Slot for a numeric object hilcal reads (and writes, ``write``); MappingError for a type mismatch, an
    access that does not allow it or an integer object without a scale."""
    name = f"{ref} ({variable.qualname}, {TYPE_NAMES.get(variable.data_type, variable.data_type)})"
    if variable.data_type not in datatypes.NUMBER_TYPES:
        raise MappingError(f"{key}: {name} in {source} is not a number")
    if not variable.readable:
        raise MappingError(f"{key}: {name} in {source} cannot be read (access {variable.access_type})")
    if write and (not variable.writable or variable.access_type == "const"):
        raise MappingError(f"{key}: {name} in {source} is read-only (access {variable.access_type}); hilcal writes it")
    if scale is None:
        if unit_scale_needed and variable.data_type not in datatypes.FLOAT_TYPES:
            raise MappingError(f"{key}: {name} is an integer: give the group's scale (device units per unit, e.g. "
                               "1000 for µm)")
        scale = 1.0
    return Slot(key, ref, node, variable, scale)
