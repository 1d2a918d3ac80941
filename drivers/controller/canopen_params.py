"""The parameter interface of a CANopen controller: the geometry and compensation terms it holds, read and written
by SDO through the station's mapping, the upload as a transaction as far as a device without staging allows.

``upload``: refuse unless the controller is disabled (every device-control node); read and record the old values of
every mapped object; write every value (an SDO abort is named with its CiA 301 meaning); read every value back, and
the checksum object if mapped; store with 1010h "save" when asked (CiA 301 v4.2.0 §7.5.2.13). On any failure after
the first write the old values are written back and read back, and the record says which writes happened and which
put the old values back. ``rollback`` writes back the set before the last upload, which the device does not keep:
the caller passes that upload's record (``previous_params``; ``procedures.records.uploads`` finds it by ``device``).
Parts of the geometry the device does not hold are the robot file's; an upload that would change them is refused.
"""

from __future__ import annotations

import hashlib
import math
from collections.abc import Sequence
from typing import Any, Literal

import numpy as np
import structlog

from drivers.controller.base import ParameterInterface
from drivers.controller.canopen_link import CanopenLink, SdoFailure
from drivers.controller.canopen_mapping import Slot, TableSlot, drive_state
from drivers.controller.canopen_resolved import GEOMETRY_PARTS, Resolved
from drivers.controller.parameter_sets import (
    CapabilityError,
    CompensationBlock,
    Identity,
    IdentityError,
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
from hilcal.protocols.compensation import LEG_FIELDS, NEEDS_FORCE, NEEDS_TEMPERATURE
from hilcal.protocols.controller_states import ControllerState
from hilcal.protocols.registers import Capability
from hilcal.robot import Robot

log = structlog.get_logger(__name__)

SAME_MM = 1e-6
"""A part of the geometry the device does not hold counts as unchanged within this (float rounding)."""
DISABLED_STATES = {"not_ready", "switch_on_disabled", "ready", "switched_on", "at_rest"}
"""Statusword states in which parameters change: CiA 402's not enabled ones, or at rest for a device without power
states (``device_control.power_states = false``)."""


class SdoAbortError(ParamsError):
    """The device refused an SDO request; ``code`` the abort code (CiA 301 table 22, named in the message)."""

    def __init__(self, message: str, code: int) -> None:
        super().__init__(message)
        self.code = code


class NoPreviousSet(ParamsError):
    """A rollback without the record of an upload that holds the set before it; nothing written."""


class CanopenTransportError(ParamsError):
    """No answer in time (or the bus failed): a write may or may not have been executed."""


def _params_error(err: SdoFailure) -> ParamsError:
    return SdoAbortError(str(err), err.code) if err.code is not None else CanopenTransportError(str(err))


def _same(slot: Slot, a: int | float, b: int | float) -> bool:
    return slot.encode(a) == slot.encode(b)


def _sha(raws: Sequence[tuple[Slot, int | float]]) -> str:
    return hashlib.sha256(b"".join(s.encode(r) for s, r in raws)).hexdigest()


class CanopenParams(ParameterInterface):
    """A CANopen controller's parameters through a resolved mapping (see the module docstring)."""

    has_backup = False

    def __init__(self, link: CanopenLink, resolved: Resolved, robot: Robot) -> None:
        self.link = link
        self.map = resolved
        self.robot = robot
        self.endpoint = link.endpoint
        self.device_id = resolved.nodes[0]
        self.records: list[UploadRecord] = []
        self._nominal = ParameterSet.from_robot(robot).to_vector()

    def close(self) -> None:
        self.link.close()

    # ------------------------------------------------------------------ reads

    def _read(self, slot: Slot) -> int | float:
        try:
            return self.link.read(slot)
        except SdoFailure as err:
            raise _params_error(err) from None

    def read_identity(self) -> Identity:
        """1018h of the first node and what the mapping makes of the device; IdentityError if the mapping's
        identity check fails."""
        ident = {name: int(self._read(slot)) for name, slot in self.map.identity.items()}
        check = self.map.mapping.identity
        for key in ("vendor_id", "product_code"):
            expected = getattr(check, key)
            if expected is not None and ident.get(key) != expected:
                raise IdentityError(f"not the controller the station names: 0x1018 {key} is "
                                    f"0x{ident.get(key, 0):08X}, the mapping's identity says 0x{expected:08X}")
        if check.min_revision is not None and ident.get("revision", 0) < check.min_revision:
            raise IdentityError(f"controller revision 0x{ident.get('revision', 0):08X} is older than the mapping's "
                                f"min_revision 0x{check.min_revision:08X}")
        return Identity(magic=0, protocol_version=0, firmware_version=ident.get("revision", 0),
                        serial_number=ident.get("serial_number", 0), capabilities=self.capabilities(),
                        parameter_count=sum(len(s) for s in self.map.geometry.values()),
                        vendor_id=ident.get("vendor_id"), product_code=ident.get("product_code"),
                        node_id=self.device_id)

    def capabilities(self) -> Capability:
        """What the mapping lets hilcal write and read (the Modbus capability bits, for the engine)."""
        caps = Capability(0)
        parts = set(self.map.geometry)
        if parts == set(GEOMETRY_PARTS):
            caps |= Capability.FULL_GEOMETRY
        elif parts == {"l0_mm"}:
            caps |= Capability.OFFSETS_ONLY
        if self.map.store is not None:
            caps |= Capability.NONVOLATILE_SAVE
        if self.map.compensation:
            caps |= Capability.COMPENSATION
        if self.map.forces is not None:
            caps |= Capability.FORCE_READING
        if self.map.temperature is not None:
            caps |= Capability.TEMPERATURE_READING
        return caps

    def device_key(self, identity: Identity) -> str:
        return (f"canopen:{identity.vendor_id or 0:08x}:{identity.product_code or 0:08x}:"
                f"{identity.serial_number:08x}@{self.device_id}")

    def node_states(self) -> dict[int, str]:
        dc = self.map.mapping.device_control
        return {n: drive_state(int(self._read(slot)), dc) for n, slot in self.map.statusword.items()}

    def read_state(self) -> ControllerState:
        """DISABLED when every node is disabled; FAULT/ESTOP when any node is; else ENABLED (or MOVING)."""
        states = set(self.node_states().values())
        if states & {"fault", "fault_reaction"}:
            return ControllerState.FAULT
        if "quick_stop" in states:
            return ControllerState.ESTOP
        if states <= DISABLED_STATES:
            return ControllerState.DISABLED
        return ControllerState.ENABLED

    def _raws(self, slots: Sequence[Slot]) -> list[tuple[Slot, Any]]:
        """Each slot's raw value; a table is not read while the table points object says 0 (empty)."""
        out: list[tuple[Slot, Any]] = []
        points = None
        for s in slots:
            if isinstance(s, TableSlot) and points == 0:
                out.append((s, b""))
                continue
            out.append((s, self._read(s)))
            if s is self.map.table_points:
                points = int(out[-1][1])
        return out

    def _geometry_from(self, raws: dict[Slot, int | float]) -> ParameterSet:
        vector = self._nominal.copy()
        start = {"a_mm": 0, "b_mm": 18, "l0_mm": 36}
        for part, slots in self.map.geometry.items():
            for k, s in enumerate(slots):
                vector[start[part] + k] = s.value(raws[s])
        return ParameterSet.from_vector(vector)

    def _block_from(self, raws: dict[Slot, int | float]) -> CompensationBlock:
        block = CompensationBlock.zero().to_block()
        for term, slots in self.map.compensation.items():
            block[term] = [s.value(raws[s]) for s in slots]
        ref = self.map.reference_temperature
        if ref is not None:
            block["reference_temperature_c"] = ref.value(raws[ref])
        if self.map.tables and self.map.table_points is not None:
            n = int(raws[self.map.table_points])
            block["table_mm"] = [t.value(raws[t])[:n] if n else [] for t in self.map.tables]
        return CompensationBlock.from_block(block)

    def read_live(self) -> ParameterSet:
        """The geometry in use: the mapped parts from the device, the others the robot file's."""
        return self._geometry_from(dict(self._raws(self.map.geometry_slots())))

    def read_live_compensation(self) -> CompensationBlock:
        if not self.map.compensation:
            raise CapabilityError("this controller's mapping holds no compensation terms")
        return self._block_from(dict(self._raws(self.map.compensation_slots())))

    def read_leg_forces_kn(self) -> np.ndarray:
        if self.map.forces is None:
            raise CapabilityError("this controller's mapping has no leg forces (controller.readings.forces_kn)")
        return np.array([s.value(self._read(s)) for s in self.map.forces])

    def read_temperature_c(self) -> float:
        if self.map.temperature is None:
            raise CapabilityError("this controller's mapping has no temperature (controller.readings.temperature_c)")
        return self.map.temperature.value(self._read(self.map.temperature))

    def read_checksum(self) -> int | None:
        """The device's checksum object (None: none mapped)."""
        return None if self.map.checksum is None else int(self._read(self.map.checksum))

    def describe(self) -> dict[str, Any]:
        """Identity, state (per node too), live geometry, compensation and checksum as plain data (``hilcal
        check``); the checksum with the value the live geometry should give."""
        identity = self.read_identity()
        raws = dict(self._raws(self.map.geometry_slots()))
        live = self._geometry_from(raws)
        checksum = self.read_checksum()
        return {
            "endpoint": self.endpoint, "device": self.device_key(identity), "identity": identity.as_dict(),
            "state": self.read_state().name, "nodes": {str(n): s for n, s in self.node_states().items()},
            "geometry": live.model_dump(), "geometry_mapped": sorted(self.map.geometry),
            "compensation": self.read_live_compensation().model_dump() if self.map.compensation else None,
            "checksum": None if checksum is None else f"{checksum:08x}",
            "checksum_expected": None if checksum is None else
            f"{self.map.checksum_of(raws, live.to_vector().tolist()):08x}",
        }

    # ------------------------------------------------------------------ transactions

    def _begin(self, operation: Literal["upload", "rollback", "save"]) -> tuple[UploadRecord, list[tuple[Slot, Any]]]:
        record = UploadRecord(operation=operation, endpoint=self.endpoint, device_id=self.device_id,
                              started_at=now_utc())
        self.records.append(record)
        try:
            identity = self.read_identity()
            record.identity = identity.as_dict()
            record.device = self.device_key(identity)
            record.offsets_only = identity.offsets_only
            state = self.read_state()
            if state is not ControllerState.DISABLED:
                raise NotDisabled(f"controller is {state.name} ({self._states_text()}): parameters change only while "
                                  "disabled; nothing written")
            old = self._raws(self.map.parameter_slots())
            raws = dict(old)
            previous = self._geometry_from(raws)
            record.previous_params = previous.model_dump()
            record.previous_live_sha256 = previous.sha256()
            record.previous_live_crc32 = f"{previous.crc32():08x}"
            if self.map.compensation:
                block = self._block_from(raws)
                record.previous_compensation = block.model_dump()
                record.previous_compensation_sha256 = block.sha256()
        except ParamsError as err:
            self._finish(record, err)
            raise
        return record, old

    def _states_text(self) -> str:
        return ", ".join(f"node {n} {s}" for n, s in self.node_states().items())

    def _finish(self, record: UploadRecord, err: ParamsError | None,
                outcome: Literal["committed", "rolled_back", "saved"] = "committed") -> None:
        record.finished_at = now_utc()
        if err is None:
            record.outcome = outcome
            log.info("canopen_params", operation=record.operation, outcome=outcome, writes=len(record.writes))
            return
        refused = isinstance(err, NotDisabled | CapabilityError | ParameterValidationError | IdentityError |
                             UploadRefused | NoPreviousSet) and not record.writes
        record.outcome = "refused" if refused else "failed"
        record.error = f"{type(err).__name__}: {err}"
        err.record = record
        log.warning("canopen_params", operation=record.operation, outcome=record.outcome, error=record.error)

    def _targets(self, params: ParameterSet, block: CompensationBlock | None, live: ParameterSet
                 ) -> list[tuple[Slot, int | float]]:
        """(slot, raw) of every value to write; CapabilityError/ParameterValidationError before anything is sent."""
        vector, held = params.to_vector(), live.to_vector()
        start = {"a_mm": 0, "b_mm": 18, "l0_mm": 36}
        for part, (lo, n) in {"a_mm": (0, 18), "b_mm": (18, 18), "l0_mm": (36, 6)}.items():
            if part not in self.map.geometry and np.max(np.abs(vector[lo:lo + n] - held[lo:lo + n])) > SAME_MM:
                raise CapabilityError(f"this controller does not hold {part} (its mapping has no "
                                      f"controller.geometry.{part}): the set changes it; nothing written")
        out: list[tuple[Slot, int | float]] = []
        try:
            for part, slots in self.map.geometry.items():
                out += [(s, s.raw(float(vector[start[part] + k]))) for k, s in enumerate(slots)]
            if block is not None:
                out += self._block_targets(block)
        except ValueError as err:
            raise ParameterValidationError(f"{err}; nothing written") from None
        order = {s: k for k, s in enumerate(self.map.parameter_slots())}
        return sorted(out, key=lambda pair: order[pair[0]])

    def _block_targets(self, block: CompensationBlock) -> list[tuple[Slot, int | float]]:
        caps = self.capabilities()
        if any(any(getattr(block, n)) for n in NEEDS_FORCE) and Capability.FORCE_READING not in caps:
            raise CapabilityError("the compensation block's compliance terms need the leg forces, which this "
                                  "controller's mapping does not read; nothing written")
        if any(any(getattr(block, n)) for n in NEEDS_TEMPERATURE) and Capability.TEMPERATURE_READING not in caps:
            raise CapabilityError("the compensation block's thermal terms need the temperature, which this "
                                  "controller's mapping does not read; nothing written")
        tables = [list(row) for row in block.table_mm]
        if self.map.tables:
            points = len(tables[0])
            out_tables: list[tuple[Slot, Any]] = [(self.map.table_points, self.map.table_points.raw(points))]
            if points:
                out_tables += [(t, t.raw(row)) for t, row in zip(self.map.tables, tables, strict=True)]
        elif any(v != 0.0 for row in tables for v in row):
            raise CapabilityError("the compensation block has stroke tables, which this controller's mapping does "
                                  "not hold; nothing written")
        out: list[tuple[Slot, int | float]] = []
        for term in LEG_FIELDS:
            values = getattr(block, term)
            if term in self.map.compensation:
                out += [(s, s.raw(v)) for s, v in zip(self.map.compensation[term], values, strict=True)]
            elif any(v != 0.0 for v in values):
                raise CapabilityError(f"this controller does not hold the compensation term {term} (no "
                                      f"controller.compensation.{term}); nothing written")
        ref = self.map.reference_temperature
        if ref is not None:
            out.append((ref, ref.raw(block.reference_temperature_c)))
        elif any(any(getattr(block, n)) for n in NEEDS_TEMPERATURE) and not math.isclose(
                block.reference_temperature_c, 20.0):
            raise CapabilityError("the block's reference temperature is not 20 °C and the controller's mapping "
                                  "has no controller.compensation.reference_temperature_c; nothing written")
        return out + (out_tables if self.map.tables else [])

    def _write(self, log_to: list[WriteRecord], slot: Slot, raw: int | float) -> None:
        ref = slot.ref.on(slot.node)
        entry = WriteRecord(function="sdo_download", address=ref.index << 8 | ref.subindex, count=1, at=now_utc(),
                            object=f"{ref} {slot.key}")
        log_to.append(entry)
        try:
            self.link.write(slot, raw)
        except SdoFailure as err:
            entry.error = str(err)
            raise _params_error(err) from None
        entry.ok = True

    def _apply(self, record: UploadRecord, targets: list[tuple[Slot, int | float]],
               old: dict[Slot, int | float], checksum_for: ParameterSet | None, save: bool) -> None:
        """Write, read back, check the checksum, store; on a failure put the old values back (see the module
        docstring) and raise."""
        try:
            for slot, raw in targets:
                self._write(record.writes, slot, raw)
            back = dict(self._raws([s for s, _ in targets]))
            bad = [str(s) for s, raw in targets if not _same(s, back[s], raw)]
            record.live_readback_match = not bad
            if bad:
                raise ReadbackMismatch(f"read back differs at {', '.join(bad[:4])}")
            if self.map.checksum is not None and checksum_for is not None:
                expected = self.map.checksum_of({**old, **dict(targets)}, checksum_for.to_vector().tolist())
                held = self.read_checksum()
                record.checksum_match = held == expected
                if not record.checksum_match:
                    raise ReadbackMismatch(f"checksum object {self.map.checksum} holds {held:08x}, the set written "
                                           f"gives {expected:08x}")
            if save:
                self._store(record)
        except ParamsError as err:
            if record.writes:
                self._restore(record, targets, old)
                err.args = (f"{err}; {self._restore_text(record)}",)
            raise

    def _store(self, record: UploadRecord) -> None:
        if self.map.store is None:
            raise CapabilityError("this controller's mapping has no store object (controller.store)")
        before = dict(self._raws(self.map.parameter_slots()))
        for slot in self.map.stores:
            self._write(record.writes, slot, self.map.mapping.store.signature)
        after = dict(self._raws(list(before)))
        record.saved_readback_match = all(_same(s, after[s], before[s]) for s in before)
        if not record.saved_readback_match:
            raise ReadbackMismatch("the values changed while the device stored them")
        record.saved = True

    def _restore(self, record: UploadRecord, targets: list[tuple[Slot, int | float]],
                 old: dict[Slot, int | float]) -> None:
        """Write the old value of every slot an attempted write touched, then read them all back."""
        written = sum(1 for w in record.writes if not (w.object or "").endswith("store.object"))
        touched = [s for s, _ in targets][:written]
        ok = True
        for slot in touched:
            try:
                self._write(record.restore_writes, slot, old[slot])
            except ParamsError:
                ok = False
        try:
            back = dict(self._raws(touched))
            record.restored_readback_match = ok and all(_same(s, back[s], old[s]) for s in touched)
        except ParamsError:
            record.restored_readback_match = False

    @staticmethod
    def _restore_text(record: UploadRecord) -> str:
        done = sum(w.ok for w in record.writes)
        if record.restored_readback_match:
            return (f"{done} of {len(record.writes)} writes had happened; the old values were written back "
                    f"({len(record.restore_writes)} writes) and read back equal")
        return (f"{done} of {len(record.writes)} writes had happened; PUTTING THE OLD VALUES BACK FAILED "
                f"({sum(w.ok for w in record.restore_writes)} of {len(record.restore_writes)} restore writes): the "
                "device may hold a mix; run hilcal rollback or hilcal upload again once it answers")

    def upload(self, params: ParameterSet | Sequence[float] | np.ndarray, *, save: bool = False,
               compensation: CompensationBlock | None = None) -> UploadRecord:
        """Write, read back (and store with ``save``) a geometry and the block's mapped terms (see the module
        docstring); without a block the device keeps its terms."""
        target = params if isinstance(params, ParameterSet) else ParameterSet.from_vector(params)
        record, old_pairs = self._begin("upload")
        old = dict(old_pairs)
        record.params_sha256 = target.sha256()
        record.params_crc32 = f"{target.crc32():08x}"
        try:
            if save and self.map.store is None:
                raise CapabilityError("this controller's mapping has no store object: upload without save")
            targets = self._targets(target, compensation, self._geometry_from(old))
            if compensation is not None:
                record.compensation_sha256 = compensation.sha256()
                record.compensation_crc32 = f"{compensation.crc32():08x}"
            record.staged_registers = len(targets)
            self._apply(record, targets, old, target, save)
            if compensation is not None:
                record.compensation_readback_match = record.live_readback_match
            record.live_after_sha256 = self.read_live().sha256()
        except ParamsError as err:
            self._finish(record, err)
            raise
        self._finish(record, None, "committed")
        return record

    def save(self) -> UploadRecord:
        """Store the live values with 1010h (controller disabled)."""
        record, _ = self._begin("save")
        try:
            self._store(record)
        except ParamsError as err:
            self._finish(record, err)
            raise
        self._finish(record, None, "saved")
        return record

    def rollback(self, last_upload: UploadRecord | None = None) -> UploadRecord:
        """Write back the set before ``last_upload`` (its ``previous_params`` and ``previous_compensation``), read
        it back, and store it when that upload was stored. Refused without a record that holds a previous set."""
        record, old_pairs = self._begin("rollback")
        old = dict(old_pairs)
        try:
            if last_upload is None or last_upload.previous_params is None:
                raise NoPreviousSet("this controller keeps no backup set: a rollback needs the record of its last "
                                    "upload (hilcal rollback finds it in the records by the device's identity); "
                                    "nothing written")
            if last_upload.device is not None and last_upload.device != record.device:
                raise NoPreviousSet(f"the upload record is of {last_upload.device}, this is {record.device}; "
                                    "nothing written")
            previous = ParameterSet.model_validate(last_upload.previous_params)
            block = (CompensationBlock.model_validate(last_upload.previous_compensation)
                     if last_upload.previous_compensation is not None and self.map.compensation else None)
            record.params_sha256 = previous.sha256()
            record.params_crc32 = f"{previous.crc32():08x}"
            targets = self._targets(previous, block, self._geometry_from(old))
            self._apply(record, targets, old, previous, bool(last_upload.saved) and self.map.store is not None)
            record.live_after_sha256 = self.read_live().sha256()
        except ParamsError as err:
            self._finish(record, err)
            raise
        self._finish(record, None, "rolled_back")
        return record
