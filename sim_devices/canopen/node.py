"""One simulated CANopen node: canopen's ``LocalNode`` (object dictionary from the EDS, SDO server) with the NMT
slave, heartbeat producer, EMCY producer, error objects, PDOs and store/restore run here (CiA 301).

canopen's ``LocalNode`` keeps the object dictionary and serves SDO (expedited and segmented; block upload falls
back to segmented, block download is refused as CiA 301 allows). Its NMT slave does not boot (no boot-up message
after a reset, no reset of the object dictionary), so this module runs NMT itself: a reset keeps the node silent for
BOOT_TIME_S, then the objects are loaded (defaults, then what 1010h stored), boot-up message 700h+id [00h] and
PRE-OPERATIONAL; the five NMT commands of CiA 301 7.2.8.3.1, SDO refused in STOPPED (no
answer), PDOs only in OPERATIONAL, heartbeat 700h+id [state] every 1017h ms. EMCY (CiA 301 7.2.7) on 80h+id with
the error register (1001h) and the pre-defined error field (1003h: newest first, eight entries, cleared by writing
0 to sub-index 0), no sooner than the inhibit time 1015h after the last one. 1010h/1011h take the signatures
"save" (65766173h) and "load" (64616F6Ch), else abort 08000020h; a restore takes effect at the next reset
(CiA 301 7.5.2.13-14). Device-specific behaviour comes from subclasses (``hexapod_node``, ``leg_drives``).
"""

from __future__ import annotations

import struct
from collections.abc import Callable
from enum import IntEnum
from pathlib import Path
from typing import Any, Protocol

import canopen
import structlog
from canopen.objectdictionary import ODArray, ODRecord, ODVariable
from canopen.sdo import SdoAbortedError

from sim_devices.canopen.nvram import Category, Nvram
from sim_devices.canopen.pdo import TPDO_MAP, PdoEngine, SdoAbort

log = structlog.get_logger(__name__)

SAVE_SIGNATURE = 0x65766173
"""'save' as UNSIGNED32 (CiA 301 7.5.2.13)."""
LOAD_SIGNATURE = 0x64616F6C
"""'load' as UNSIGNED32 (CiA 301 7.5.2.14)."""
ERROR_HISTORY = 8
NOT_STORED = frozenset({0x1003, 0x1010, 0x1011})
SYNC_DEFAULT = 0x80
BOOT_TIME_S = 0.02
"""How long a reset keeps the node silent before its boot-up message (real time)."""


class NmtState(IntEnum):
    """NMT states as the heartbeat carries them (CiA 301 7.2.8.3.2)."""

    INITIALISING = 0x00
    STOPPED = 0x04
    OPERATIONAL = 0x05
    PRE_OPERATIONAL = 0x7F


class NmtCommand(IntEnum):
    """NMT command specifiers (CiA 301 7.2.8.3.1)."""

    START = 0x01
    STOP = 0x02
    ENTER_PRE_OPERATIONAL = 0x80
    RESET_NODE = 0x81
    RESET_COMMUNICATION = 0x82


class FrameSink(Protocol):
    """Where a node's frames go (``bus.FrameOutbox``); also the ``network`` of the LocalNode's SDO server."""

    def send_message(self, can_id: int, data: bytes, remote: bool = False) -> None: ...


Reader = Callable[[int], Any]
Writer = Callable[[int, bytes], None]


class SimulatedNode:
    """A CANopen node on a FrameSink (see the module docstring); ``readers``/``writers`` hold the device's objects
    (index -> function of the sub-index), the rest of the dictionary is plain data kept by the LocalNode."""

    def __init__(self, node_id: int, eds_path: Path, sink: FrameSink, nvram: Nvram) -> None:
        self.id = node_id
        self.od = canopen.import_od(str(eds_path), node_id)
        self.local = canopen.LocalNode(node_id, self.od)
        # The LocalNode's own NMT slave would start canopen's heartbeat task on a 1017h write; this module runs the
        # heartbeat itself, so that callback is taken out (canopen registers it as the only write callback).
        self.local._write_callbacks.clear()
        self.local.add_read_callback(self._on_read)
        self.local.add_write_callback(self._on_write)
        self.local.sdo.network = sink
        self.sink = sink
        self.nvram = nvram
        self.log = log.bind(node=node_id)
        self.pdo = PdoEngine(self)
        self.nmt = NmtState.INITIALISING
        self.readers: dict[int, Reader] = {
            0x1001: lambda _: self.error_register, 0x1003: self._read_errors,
            0x1010: self._read_capability, 0x1011: self._read_capability}
        self.writers: dict[int, Writer] = {0x1003: self._write_errors, 0x1010: self._write_store,
                                           0x1011: self._write_restore}
        self.error_register = 0
        self.errors: list[int] = []
        self._heartbeat_s = 0.0
        self._next_heartbeat = 0.0
        self._emcy_queue: list[bytes] = []
        self._emcy_last = -1e9
        self._pending_reset: tuple[float, bool] | None = None
        self._sync_cob_id: int | None = None
        self.now = 0.0

    # ------------------------------------------------------------------ object access

    def variable(self, index: int, sub: int) -> ODVariable:
        obj = self.od[index]
        if isinstance(obj, ODRecord | ODArray):
            obj = obj[sub]
        assert isinstance(obj, ODVariable)
        return obj

    def value(self, index: int, sub: int = 0) -> Any:
        """An object's value as the host would read it."""
        return self.variable(index, sub).decode_raw(self.local.get_data(index, sub))

    def set_value(self, index: int, sub: int, value: Any) -> None:
        """Put a value into the dictionary without the write checks (the device's own update)."""
        self.local.data_store.setdefault(index, {})[sub] = self.variable(index, sub).encode_raw(value)

    def _on_read(self, index: int, subindex: int, od: ODVariable) -> Any:
        reader = self.readers.get(index)
        return None if reader is None else reader(subindex)

    def _on_write(self, index: int, subindex: int, od: ODVariable, data: bytes) -> None:
        self.pdo.check_write(index, subindex, bytes(data))
        writer = self.writers.get(index)
        if writer is not None:
            writer(subindex, bytes(data))
        if 0x1400 <= index <= TPDO_MAP + 0xFF:
            self.pdo.invalidate()
        if index == 0x1005:
            self._sync_cob_id = None
        if index == 0x1017:
            self._heartbeat_s = int.from_bytes(data, "little") / 1000.0
            self._next_heartbeat = self.now + self._heartbeat_s

    # ------------------------------------------------------------------ frames

    def send(self, can_id: int, data: bytes) -> None:
        self.sink.send_message(can_id, data)

    def handle(self, can_id: int, data: bytes, now: float) -> bool:
        """A frame from the bus; True if it was for this node."""
        self.now = now
        if can_id == 0x000:
            if len(data) == 2 and data[1] in (0, self.id):
                self._nmt_command(data[0], now)
            return False
        if can_id == self.sync_cob_id():
            if self.nmt is NmtState.OPERATIONAL:
                self.pdo.on_sync(now)
            return False
        if can_id == 0x600 + self.id:
            if self.nmt in (NmtState.PRE_OPERATIONAL, NmtState.OPERATIONAL) and len(data) == 8:
                self.local.sdo.on_request(can_id, bytearray(data), now)
            return True
        if self.nmt is NmtState.OPERATIONAL:
            n = self.pdo.rpdo_for(can_id)
            if n is not None:
                self.pdo.on_rpdo(n, bytes(data))
                return True
        return False

    def sync_cob_id(self) -> int:
        """The COB-ID of SYNC (1005h), read once per change."""
        if self._sync_cob_id is None:
            self._sync_cob_id = int(self.value(0x1005)) & 0x7FF if 0x1005 in self.od else SYNC_DEFAULT
        return self._sync_cob_id

    def tick(self, now: float) -> None:
        """Timers: heartbeat, delayed EMCY, event-driven TPDOs, then the device's own."""
        self.now = now
        if self.nmt is NmtState.INITIALISING:
            if self._pending_reset is not None and now >= self._pending_reset[0]:
                self._boot(now)
            return
        if self._heartbeat_s > 0 and now >= self._next_heartbeat:
            self.send(0x700 + self.id, bytes([self.nmt]))
            self._next_heartbeat = max(self._next_heartbeat + self._heartbeat_s, now)
        self.device_tick(now)
        if self._emcy_queue and now - self._emcy_last >= self._emcy_inhibit_s():
            self._emcy_last = now
            self.send(0x80 + self.id, self._emcy_queue.pop(0))
        if self.nmt is NmtState.OPERATIONAL:
            self.pdo.tick(now)

    # ------------------------------------------------------------------ NMT

    def power_on(self, now: float) -> None:
        """Power-up: initialise every object from the defaults and the non-volatile memory, boot up."""
        self._reset(now, communication_only=False)
        self._boot(now)

    def _reset(self, now: float, communication_only: bool) -> None:
        """Start a reset: the node goes silent for BOOT_TIME_S (``tick`` finishes it), as a device's boot takes."""
        old = self.nmt
        self.nmt = NmtState.INITIALISING
        self.nmt_changed(old, self.nmt)
        self._pending_reset = (now + BOOT_TIME_S, communication_only)

    def _boot(self, now: float) -> None:
        """Finish a reset: load the objects, send the boot-up message, enter PRE-OPERATIONAL."""
        assert self._pending_reset is not None
        communication_only = self._pending_reset[1]
        self._pending_reset = None
        if communication_only:
            for index in [i for i in self.local.data_store if 0x1000 <= i <= 0x1FFF]:
                del self.local.data_store[index]
            stored = {k: v for k, v in self.nvram.entries(self.id).items() if 0x1000 <= k[0] <= 0x1FFF}
        else:
            self.local.data_store.clear()
            self.errors, self.error_register = [], 0
            stored = self.nvram.entries(self.id)
            self.reset_application()
        for (index, sub), data in stored.items():
            if index in self.od:
                self.local.data_store.setdefault(index, {})[sub] = data
        self.pdo.invalidate()
        self._sync_cob_id = None
        self._emcy_queue.clear()
        self._heartbeat_s = int(self.value(0x1017)) / 1000.0
        self.send(0x700 + self.id, bytes([NmtState.INITIALISING]))
        self._next_heartbeat = now + self._heartbeat_s
        self._enter(NmtState.PRE_OPERATIONAL, now)

    def _enter(self, state: NmtState, now: float) -> None:
        old, self.nmt = self.nmt, state
        if old is not state:
            self.log.info("nmt_state", state=state.name)
            if state is NmtState.OPERATIONAL:
                self.pdo.start(now)
            self.nmt_changed(old, state)

    def _nmt_command(self, command: int, now: float) -> None:
        if command == NmtCommand.RESET_NODE:
            self._reset(now, communication_only=False)
        elif command == NmtCommand.RESET_COMMUNICATION:
            self._reset(now, communication_only=True)
        elif self.nmt is not NmtState.INITIALISING:
            target = {NmtCommand.START: NmtState.OPERATIONAL, NmtCommand.STOP: NmtState.STOPPED,
                      NmtCommand.ENTER_PRE_OPERATIONAL: NmtState.PRE_OPERATIONAL}.get(command)  # type: ignore[call-overload]
            if target is not None:
                self._enter(target, now)

    # ------------------------------------------------------------------ errors and EMCY

    def _emcy_inhibit_s(self) -> float:
        return int(self.value(0x1015)) * 100e-6 if 0x1015 in self.od else 0.0

    def emcy(self, code: int, register: int, manufacturer: bytes = b"") -> None:
        """Send an EMCY (PRE-OPERATIONAL and OPERATIONAL only; queued behind the inhibit time)."""
        if self.nmt not in (NmtState.PRE_OPERATIONAL, NmtState.OPERATIONAL):
            return
        frame = struct.pack("<HB", code, register) + bytes(manufacturer[:5]).ljust(5, b"\0")
        self._emcy_queue.append(frame)
        self.log.info("emcy", code=f"{code:04X}", register=f"{register:02X}")

    def raise_error(self, code: int, register_bits: int, manufacturer: bytes = b"") -> None:
        """An error occurred: error register (generic bit 0 and ``register_bits``), 1003h, EMCY."""
        self.error_register = 0x01 | register_bits
        self.errors = [code, *self.errors][:ERROR_HISTORY]
        self.emcy(code, self.error_register, manufacturer)

    def clear_errors(self) -> None:
        """Every error is gone: error register 0, EMCY 0000h (error reset); 1003h keeps the history."""
        if self.error_register:
            self.error_register = 0
            self.emcy(0x0000, 0)

    def _read_errors(self, sub: int) -> int:
        if sub == 0:
            return len(self.errors)
        return self.errors[sub - 1] if sub <= len(self.errors) else 0

    def _write_errors(self, sub: int, data: bytes) -> None:
        if sub != 0 or int.from_bytes(data, "little") != 0:
            raise SdoAbortedError(SdoAbort.VALUE_RANGE)
        self.errors = []

    # ------------------------------------------------------------------ store and restore

    @staticmethod
    def _read_capability(sub: int) -> int | None:
        """1010h/1011h read: 1 = the device stores (restores) on command; sub-index 0 from the EDS."""
        return None if sub == 0 else 1

    def _write_store(self, sub: int, data: bytes) -> None:
        if int.from_bytes(data, "little") != SAVE_SIGNATURE:
            raise SdoAbortedError(SdoAbort.CANNOT_STORE)
        categories = Category.of_sub_index(sub)
        self.store(categories)
        values: dict[tuple[int, int], bytes] = {}
        for category in categories:
            values.update(self._stored_values(category))
        self.nvram.put(self.id, categories, values)
        self.log.info("parameters_stored", categories=[c.name for c in categories])

    def _write_restore(self, sub: int, data: bytes) -> None:
        if int.from_bytes(data, "little") != LOAD_SIGNATURE:
            raise SdoAbortedError(SdoAbort.CANNOT_STORE)
        categories = Category.of_sub_index(sub)
        self.restore_defaults(categories)
        self.nvram.put(self.id, categories, {})
        self.log.info("defaults_restored", categories=[c.name for c in categories], effective="at the next reset")

    def _stored_values(self, category: Category) -> dict[tuple[int, int], bytes]:
        """The plain-data objects of a category the node keeps over a reset (rw, not process data)."""
        out = {}
        for index in self.od:
            if not category.contains(index) or index in NOT_STORED or index in self.readers:
                continue
            obj = self.od[index]
            members = list(obj.values()) if isinstance(obj, ODRecord | ODArray) else [obj]
            for var in members:
                if var.access_type == "rw":
                    out[(index, var.subindex)] = bytes(self.local.get_data(index, var.subindex))
        return out

    # ------------------------------------------------------------------ device hooks

    def reset_application(self) -> None:
        """Reset node: the device loads its application from non-volatile memory (subclasses)."""

    def store(self, categories: tuple[Category, ...]) -> None:
        """1010h: keep the device's own objects of these categories (subclasses; SdoAbortedError refuses)."""

    def restore_defaults(self, categories: tuple[Category, ...]) -> None:
        """1011h: the device's own objects of these categories are to be factory values after the next reset."""

    def nmt_changed(self, old: NmtState, new: NmtState) -> None:
        """The NMT state changed (subclasses stop motion when the node leaves service)."""

    def device_tick(self, now: float) -> None:
        """Called on every tick while the node is not initialising (subclasses: faults, EMCY)."""
