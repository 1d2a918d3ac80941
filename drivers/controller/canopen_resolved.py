"""A CANopen mapping resolved against the device's object dictionaries: every reference turned into a typed slot,
so that nothing is sent to a device whose EDS does not hold what the mapping says (``resolve``), and the CiA 402
hexapod preset (``cia402_hexapod``): six drives, one per leg, in profile position mode.
"""

from __future__ import annotations

import functools
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field

from canopen.objectdictionary import ObjectDictionary, datatypes

from drivers.controller.canopen_mapping import (
    N_LEGS,
    CanopenMapping,
    Command,
    MappingError,
    ObjectRef,
    ObjectsTable,
    Slot,
    TableSlot,
    expand,
    lookup,
    numeric,
)
from hilcal.protocols.checksums import crc32_ieee
from hilcal.protocols.compensation import LEG_FIELDS

GEOMETRY_PARTS = {"a_mm": 3 * N_LEGS, "b_mm": 3 * N_LEGS, "l0_mm": N_LEGS}
IDENTITY_SUBS = {"vendor_id": 1, "product_code": 2, "revision": 3, "serial_number": 4}
"""Object 1018h's sub-indices (CiA 301 v4.2.0 §7.5.2.22)."""


@dataclass
class Resolved:
    """The slots of every mapped object; nodes[0] is the node references without ``@`` are on."""

    mapping: CanopenMapping
    nodes: list[int]
    leg_nodes: list[int]
    source: str
    controlword: dict[int, Slot] = field(default_factory=dict)
    statusword: dict[int, Slot] = field(default_factory=dict)
    mode: dict[int, tuple[Slot, Slot]] = field(default_factory=dict)
    setpoints: list[Slot] = field(default_factory=list)
    apply: Slot | None = None
    apply_result: Slot | None = None
    actual: list[Slot] = field(default_factory=list)
    geometry: dict[str, list[Slot]] = field(default_factory=dict)
    compensation: dict[str, list[Slot]] = field(default_factory=dict)
    reference_temperature: Slot | None = None
    table_points: Slot | None = None
    tables: list[TableSlot] = field(default_factory=list)
    forces: list[Slot] | None = None
    temperature: Slot | None = None
    checksum: Slot | None = None
    store: Slot | None = None
    restore: Slot | None = None
    stores: list[Slot] = field(default_factory=list)
    """The store object on every node that holds a mapped parameter (each node stores its own)."""
    identity: dict[str, Slot] = field(default_factory=dict)

    def parameter_slots(self) -> list[Slot]:
        """Every slot an upload writes, in order: a, b, l0, then the compensation terms."""
        out = [s for part in GEOMETRY_PARTS for s in self.geometry.get(part, [])]
        out += [s for term in LEG_FIELDS for s in self.compensation.get(term, [])]
        out += [s for s in (self.reference_temperature, self.table_points) if s is not None]
        return out + list(self.tables)

    def geometry_slots(self) -> list[Slot]:
        return [s for part in GEOMETRY_PARTS for s in self.geometry.get(part, [])]

    def compensation_slots(self) -> list[Slot]:
        return self.parameter_slots()[len(self.geometry_slots()):]

    def checksum_of(self, raws: Mapping[Slot, int | float], values_mm: Sequence[float]) -> int:
        """The checksum the device should hold for these geometry raws (``values_mm``: the 42 values)."""
        import struct

        if self.mapping.checksum is None:
            raise MappingError("controller.checksum: no checksum object mapped")
        if self.mapping.checksum.algorithm == "crc32-float32-be":
            return crc32_ieee(struct.pack(">42f", *values_mm))
        data = b"".join(s.encode(raws[s]) for part in GEOMETRY_PARTS for s in self.geometry.get(part, []))
        return crc32_ieee(data)


def resolve(mapping: CanopenMapping, dictionaries: Mapping[int, ObjectDictionary], nodes: Sequence[int],
            source: str) -> Resolved:
    """Check every reference of the mapping against the nodes' dictionaries (from their EDS/DCF, ``source`` in
    messages); MappingError naming the first key that does not fit."""
    nodes = list(nodes)
    if not nodes or len(set(nodes)) != len(nodes):
        raise MappingError(f"controller: node ids {nodes}: at least one, each once")
    leg_nodes = nodes if len(nodes) == N_LEGS else [nodes[0]] * N_LEGS
    out = Resolved(mapping, nodes, leg_nodes, source)
    primary = nodes[0]

    def one(ref_text: str, key: str, *, write: bool, scale: float | None = 1.0, node: int | None = None) -> Slot:
        ref = ObjectRef.parse(ref_text)
        if node is not None and ref.node is None:
            ref = ref.on(node)
        n, var = lookup(dictionaries, ref, primary, key, source)
        return numeric(n, var, ref, key, source, write=write, scale=scale)

    def group(objects, count: int, key: str, *, write: bool, scale: float | None) -> list[Slot]:
        try:
            refs = expand(objects, count, key, leg_nodes)
        except ValueError as err:
            raise MappingError(f"{key}: {err}") from None
        slots = []
        for k, ref in enumerate(refs):
            n, var = lookup(dictionaries, ref, primary, f"{key}[{k}]", source)
            slots.append(numeric(n, var, ref, f"{key}[{k}]", source, write=write, scale=scale))
        return slots

    dc = mapping.device_control
    for n in dc.nodes or nodes:
        out.controlword[n] = one(dc.controlword, "controller.device_control.controlword", write=True, node=n)
        out.statusword[n] = one(dc.statusword, "controller.device_control.statusword", write=False, node=n)
        if dc.operation_mode is not None:
            out.mode[n] = (one(dc.mode_object, "controller.device_control.mode_object", write=True, node=n),
                           one(dc.mode_display, "controller.device_control.mode_display", write=False, node=n))
        for key, slot in (("controlword", out.controlword[n]), ("statusword", out.statusword[n])):
            if slot.variable.data_type not in datatypes.UNSIGNED_TYPES:
                raise MappingError(f"controller.device_control.{key}: {slot} is not an unsigned integer")
    sp = mapping.setpoints
    out.setpoints = group(sp.legs, N_LEGS, "controller.setpoints.legs", write=True, scale=sp.scale)
    if sp.apply is not None:
        out.apply = one(sp.apply, "controller.setpoints.apply", write=True)
    if sp.apply_result is not None:
        out.apply_result = one(sp.apply_result, "controller.setpoints.apply_result", write=False)
    out.actual = group(mapping.actual.legs, N_LEGS, "controller.actual.legs", write=False,
                       scale=mapping.actual.scale)
    geo = mapping.geometry
    for part, count in GEOMETRY_PARTS.items():
        objects = getattr(geo, part)
        if objects is not None:
            out.geometry[part] = group(objects, count, f"controller.geometry.{part}", write=True, scale=geo.scale)
    comp = mapping.compensation
    for term in LEG_FIELDS:
        objects = getattr(comp, term)
        if objects is not None:
            out.compensation[term] = group(objects, N_LEGS, f"controller.compensation.{term}", write=True,
                                           scale=comp.scales.get(term, 1.0))
    if comp.reference_temperature_c is not None:
        out.reference_temperature = one(comp.reference_temperature_c, "controller.compensation."
                                        "reference_temperature_c", write=True,
                                        scale=comp.scales.get("reference_temperature_c", 1.0))
    if (comp.table_mm is None) != (comp.table_points is None):
        raise MappingError("controller.compensation: table_mm and table_points go together")
    if comp.table_mm is not None:
        out.table_points = one(comp.table_points, "controller.compensation.table_points", write=True)
        if len(comp.table_mm) != N_LEGS:
            raise MappingError(f"controller.compensation.table_mm: {N_LEGS} objects expected, the mapping gives "
                               f"{len(comp.table_mm)}")
        for k, text in enumerate(comp.table_mm):
            key = f"controller.compensation.table_mm[{k}]"
            ref = ObjectRef.parse(text)
            n, var = lookup(dictionaries, ref, primary, key, source)
            if var.data_type != datatypes.DOMAIN or not var.writable:
                raise MappingError(f"{key}: {ref} ({var.qualname}) in {source} is not a writable DOMAIN")
            out.tables.append(TableSlot(key, ref, n, var, comp.scales.get("table_mm", 1.0)))
    rd = mapping.readings
    if rd.forces_kn is not None:
        out.forces = group(rd.forces_kn, N_LEGS, "controller.readings.forces_kn", write=False, scale=rd.force_scale)
    if rd.temperature_c is not None:
        out.temperature = one(rd.temperature_c, "controller.readings.temperature_c", write=False,
                              scale=rd.temperature_scale)
    if mapping.checksum is not None:
        out.checksum = one(mapping.checksum.object, "controller.checksum.object", write=False)
        if out.checksum.variable.data_type not in datatypes.UNSIGNED_TYPES:
            raise MappingError(f"controller.checksum.object: {out.checksum} is not an unsigned integer")
        if not out.geometry:
            raise MappingError("controller.checksum: a checksum of the parameter set needs the geometry mapped")
    for key, command in (("store", mapping.store), ("restore", mapping.restore)):
        if command is not None:
            setattr(out, key, _command(command, f"controller.{key}.object", one))
    if mapping.store is not None:
        holders = sorted({s.node for s in out.parameter_slots()}) or [primary]
        ref = ObjectRef.parse(mapping.store.object)
        out.stores = [out.store] if ref.node is not None else [
            _command(mapping.store, "controller.store.object", functools.partial(one, node=n)) for n in holders]
    for name, sub in IDENTITY_SUBS.items():
        try:
            out.identity[name] = one(f"0x1018:{sub}", f"identity (0x1018:{sub}, CiA 301)", write=False)
        except MappingError:
            if name == "vendor_id":  # the only mandatory entry of 1018h
                raise
    return out


def _command(command: Command, key: str, one) -> Slot:
    slot = one(command.object, key, write=True)
    if slot.variable.data_type != datatypes.UNSIGNED32:
        raise MappingError(f"{key}: {slot} is not UNSIGNED32 (CiA 301 1010h/1011h entries are)")
    return slot


def cia402_hexapod(*, position_unit_mm: float, offsets: bool = True, change_immediately: bool = True,
                   emcy_codes: Mapping[str, str] | None = None) -> CanopenMapping:
    """Six CiA 402 drives, node i driving leg i (node ids: the station's ``node_ids`` in leg order): profile position
    mode (CiA 402-2 §12), 607Ah target position written by SDO, the new-setpoint handshake (controlword bit 4 raised,
    statusword bit 12 acknowledges; bit 5: change immediately), 6064h position actual value, and with ``offsets`` the
    leg offsets as 607Ch home offset. ``position_unit_mm``: what one position unit is in mm (1 µm: 0.001; raw
    increments: the feed per motor revolution over the increments per revolution, divided by the gear ratio)."""
    if not position_unit_mm > 0:
        raise MappingError("controller.position_unit_mm: what one position unit is in mm, > 0")
    scale = 1.0 / position_unit_mm
    return CanopenMapping.model_validate({
        "setpoints": {"legs": ObjectsTable(per_node="0x607A"), "scale": scale, "new_setpoint_bit": 4,
                      "change_immediately_bit": 5 if change_immediately else None, "ack_bit": 12},
        "actual": {"legs": ObjectsTable(per_node="0x6064"), "scale": scale},
        "geometry": {"l0_mm": ObjectsTable(per_node="0x607C"), "scale": scale} if offsets else {},
        "device_control": {"operation_mode": 1},
        "emcy_codes": dict(emcy_codes or {}),
    })
