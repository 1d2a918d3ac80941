"""PDOs of a simulated CANopen node, run from its object dictionary (CiA 301 7.2.2 and 7.5.2.35-7.5.2.38).

The communication (1400h-1403h, 1800h-1803h) and mapping (1600h-1603h, 1A00h-1A03h) parameters are read from the
node's object dictionary whenever they change, so a host can re-map and re-time PDOs by SDO as on a real device.
Mapping granularity is 8 bits. RPDOs: transmission types 0-240 take effect at the next SYNC, 254/255 at once; a
frame shorter than the mapping is dropped with EMCY 8210h. TPDOs: 1-240 are sent on every n-th SYNC, 0 on a SYNC
after a change, 254/255 on a change of the mapped data (no sooner than the inhibit time after the last one) and when
the event timer runs out. The SYNC start value (sub-index 6) is taken as 0. RTR-only types (252, 253) are refused.
Parameter writes are checked as CiA 301 says (abort codes in ``SdoAbort``); canopen's ``PdoMap.save`` sequence
(invalidate, re-map, validate) passes.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass, field
from typing import Any, Protocol

import canopen
from canopen.objectdictionary import ODArray, ODRecord, ODVariable
from canopen.sdo import SdoAbortedError

RPDO_COMM, RPDO_MAP, TPDO_COMM, TPDO_MAP = 0x1400, 0x1600, 0x1800, 0x1A00
N_PDOS = 4
MAX_ENTRIES = 4
PDO_BITS = 64
INVALID = 0x80000000
EXTENDED = 0x20000000
EMCY_PDO_LENGTH = 0x8210
"""CiA 301 emergency error code: PDO not processed due to length error."""
CHANGE_POLL_S = 0.01
"""Event-driven TPDOs look for a change of their data this often (real time)."""


class SdoAbort:
    """CiA 301 SDO abort codes (table 22) the simulated devices answer with."""

    UNSUPPORTED_ACCESS = 0x06010000
    WRITE_READ_ONLY = 0x06010002
    NOT_IN_OD = 0x06020000
    CANNOT_MAP = 0x06040041
    PDO_TOO_LONG = 0x06040042
    LENGTH_MISMATCH = 0x06070010
    NO_SUBINDEX = 0x06090011
    VALUE_RANGE = 0x06090030
    VALUE_TOO_HIGH = 0x06090031
    VALUE_TOO_LOW = 0x06090032
    GENERAL = 0x08000000
    CANNOT_STORE = 0x08000020
    LOCAL_CONTROL = 0x08000021
    DEVICE_STATE = 0x08000022


class PdoHost(Protocol):
    """What the engine needs of its node (``node.SimulatedNode``)."""

    od: canopen.ObjectDictionary
    local: canopen.LocalNode
    log: Any

    def value(self, index: int, sub: int = 0) -> Any: ...

    def send(self, can_id: int, data: bytes) -> None: ...

    def emcy(self, code: int, register: int, manufacturer: bytes = b"") -> None: ...


@dataclass
class PdoParams:
    """One PDO's communication and mapping parameters, decoded."""

    cob_id: int
    valid: bool
    trans_type: int
    inhibit_s: float
    event_s: float
    entries: list[tuple[int, int, int]]
    """(index, sub-index, bits) of each mapped object, in order."""

    @property
    def length(self) -> int:
        return sum(bits for _, _, bits in self.entries) // 8


@dataclass
class _TpdoState:
    last_data: bytes | None = None
    last_sent: float = -1e9
    next_event: float = 0.0
    sync_count: int = 0


@dataclass
class PdoEngine:
    """The PDOs of one node (see the module docstring)."""

    node: PdoHost
    _rpdo: list[PdoParams] | None = None
    _tpdo: list[PdoParams] | None = None
    _tx_state: list[_TpdoState] = field(default_factory=lambda: [_TpdoState() for _ in range(N_PDOS)])
    _sync_buffer: dict[int, bytes] = field(default_factory=dict)
    _next_poll: float = 0.0

    # ------------------------------------------------------------------ parameters

    def _u(self, index: int, sub: int) -> int:
        return int(self.node.value(index, sub))

    def _params(self, comm: int, mapping: int, n: int, tx: bool) -> PdoParams:
        cob = self._u(comm + n, 1)
        count = self._u(mapping + n, 0)
        entries = []
        for k in range(1, count + 1):
            raw = self._u(mapping + n, k)
            entries.append((raw >> 16, (raw >> 8) & 0xFF, raw & 0xFF))
        inhibit = self._u(comm + n, 3) * 100e-6 if tx else 0.0
        event = self._u(comm + n, 5) / 1000.0 if tx else 0.0
        return PdoParams(cob & 0x7FF, not cob & INVALID, self._u(comm + n, 2), inhibit, event, entries)

    def rpdos(self) -> list[PdoParams]:
        if self._rpdo is None:
            self._rpdo = [self._params(RPDO_COMM, RPDO_MAP, n, False) for n in range(N_PDOS)]
        return self._rpdo

    def tpdos(self) -> list[PdoParams]:
        if self._tpdo is None:
            self._tpdo = [self._params(TPDO_COMM, TPDO_MAP, n, True) for n in range(N_PDOS)]
        return self._tpdo

    def invalidate(self) -> None:
        """Forget the decoded parameters (after a write or a reset) and the TPDOs' history."""
        self._rpdo = self._tpdo = None
        self._tx_state = [_TpdoState() for _ in range(N_PDOS)]
        self._sync_buffer.clear()

    def check_write(self, index: int, sub: int, data: bytes) -> None:
        """Refuse a parameter write CiA 301 does not allow (SdoAbortedError); the caller stores it if not."""
        base = index & 0xFF00
        n = index & 0xFF
        if base not in (RPDO_COMM, RPDO_MAP, TPDO_COMM, TPDO_MAP) or n >= N_PDOS:
            return
        tx = base in (TPDO_COMM, TPDO_MAP)
        comm = (TPDO_COMM if tx else RPDO_COMM) + n
        valid = not self._u(comm, 1) & INVALID
        if base in (RPDO_COMM, TPDO_COMM):
            self._check_comm(comm, sub, data, valid, tx)
        else:
            self._check_mapping(index, sub, data, valid, tx)

    def _check_comm(self, comm: int, sub: int, data: bytes, valid: bool, tx: bool) -> None:
        value = int.from_bytes(data, "little")
        if sub == 1:
            if value & EXTENDED:
                raise SdoAbortedError(SdoAbort.VALUE_RANGE)
            if valid and not value & INVALID and (value & 0x7FF) != (self._u(comm, 1) & 0x7FF):
                raise SdoAbortedError(SdoAbort.VALUE_RANGE)
        elif sub == 2:
            if 241 <= value <= 253:
                raise SdoAbortedError(SdoAbort.VALUE_RANGE)
        elif sub == 3 and tx and valid:
            raise SdoAbortedError(SdoAbort.DEVICE_STATE)

    def _check_mapping(self, index: int, sub: int, data: bytes, valid: bool, tx: bool) -> None:
        if valid:
            raise SdoAbortedError(SdoAbort.DEVICE_STATE)
        value = int.from_bytes(data, "little")
        if sub != 0:
            if self._u(index, 0) != 0:
                raise SdoAbortedError(SdoAbort.DEVICE_STATE)
            return
        if value > MAX_ENTRIES:
            raise SdoAbortedError(SdoAbort.VALUE_TOO_HIGH)
        bits = 0
        for k in range(1, value + 1):
            raw = self._u(index, k)
            bits += self._check_entry(raw >> 16, (raw >> 8) & 0xFF, raw & 0xFF, tx)
        if bits > PDO_BITS:
            raise SdoAbortedError(SdoAbort.PDO_TOO_LONG)

    def _check_entry(self, index: int, sub: int, bits: int, tx: bool) -> int:
        od = self.node.od
        if index not in od:
            raise SdoAbortedError(SdoAbort.CANNOT_MAP)
        obj = od[index]
        if isinstance(obj, ODRecord | ODArray):
            if sub not in obj:
                raise SdoAbortedError(SdoAbort.CANNOT_MAP)
            obj = obj[sub]
        assert isinstance(obj, ODVariable)
        allowed = obj.readable if tx else obj.writable
        if not obj.pdo_mappable or not allowed or bits != len(obj):
            raise SdoAbortedError(SdoAbort.CANNOT_MAP)
        return bits

    # ------------------------------------------------------------------ traffic

    def rpdo_for(self, can_id: int) -> int | None:
        """The number (0-based) of the valid RPDO received on this COB-ID, None if none is."""
        for n, params in enumerate(self.rpdos()):
            if params.valid and params.entries and params.cob_id == can_id:
                return n
        return None

    def on_rpdo(self, n: int, data: bytes) -> None:
        """An RPDO frame (the node is OPERATIONAL): write its objects now or at the next SYNC."""
        params = self.rpdos()[n]
        if len(data) < params.length:
            self.node.emcy(EMCY_PDO_LENGTH, 0x10, struct.pack("<H", n + 1))
            return
        if params.trans_type <= 240:
            self._sync_buffer[n] = bytes(data)
        else:
            self._write(params, data)

    def _write(self, params: PdoParams, data: bytes) -> None:
        offset = 0
        for index, sub, bits in params.entries:
            size = bits // 8
            try:
                self.node.local.set_data(index, sub, data[offset:offset + size], check_writable=True)
            except SdoAbortedError as err:
                self.node.log.info("rpdo_write_refused", index=f"{index:04X}", sub=sub, code=f"{err.code:08X}")
            offset += size

    def _build(self, params: PdoParams) -> bytes:
        out = bytearray()
        for index, sub, bits in params.entries:
            out += self.node.local.get_data(index, sub)[:bits // 8]
        return bytes(out)

    def _send(self, n: int, params: PdoParams, data: bytes, now: float) -> None:
        state = self._tx_state[n]
        self.node.send(params.cob_id, data)
        state.last_data, state.last_sent = data, now
        if params.event_s > 0:
            state.next_event = now + params.event_s

    def on_sync(self, now: float) -> None:
        """A SYNC (the node is OPERATIONAL): synchronous RPDOs take effect, synchronous TPDOs are sent."""
        rpdos = self.rpdos()
        for n, data in sorted(self._sync_buffer.items()):
            self._write(rpdos[n], data)
        self._sync_buffer.clear()
        for n, params in enumerate(self.tpdos()):
            if not params.valid or not params.entries or params.trans_type > 240:
                continue
            state = self._tx_state[n]
            data = self._build(params)
            if params.trans_type == 0:
                if data != state.last_data:
                    self._send(n, params, data, now)
                continue
            state.sync_count += 1
            if state.sync_count >= params.trans_type:
                state.sync_count = 0
                self._send(n, params, data, now)

    def start(self, now: float) -> None:
        """The node entered OPERATIONAL: every event-driven TPDO is sent once."""
        self._tx_state = [_TpdoState() for _ in range(N_PDOS)]
        for n, params in enumerate(self.tpdos()):
            if params.valid and params.entries and params.trans_type >= 254:
                self._send(n, params, self._build(params), now)

    def tick(self, now: float) -> None:
        """Event-driven TPDOs: the event timer, and a change of the data (looked for every CHANGE_POLL_S)."""
        poll = now >= self._next_poll
        if poll:
            self._next_poll = now + CHANGE_POLL_S
        for n, params in enumerate(self.tpdos()):
            if not params.valid or not params.entries or params.trans_type < 254:
                continue
            state = self._tx_state[n]
            timer_due = params.event_s > 0 and now >= state.next_event
            if not (timer_due or poll):
                continue
            data = self._build(params)
            changed = data != state.last_data and now - state.last_sent >= params.inhibit_s
            if timer_due or changed:
                self._send(n, params, data, now)
