"""The HX-6 hexapod motion controller (``hexapod_controller.eds``): one CANopen node for the whole machine.

Device control by 6040h/6041h (``cia402``): OPERATION ENABLED is the controller model ENABLED (hydraulics on,
legs servoed), the states below it are DISABLED, FAULT follows a model fault or e-stop and sends its EMCY. Setpoints:
2000h sub 1-6 (mm) are held until a write to 2001h applies all six at once (in OPERATION ENABLED only, else abort
08000022h; beyond the stroke: abort 06090030h and statusword bit 11); 2002h echoes the applied value, 2003h the
result. Geometry (2100h-2115h records, 2120h offsets) and compensation (2200h-2207h, stroke tables 2210h-2215h) are
the model's live set, changed at once (``model``); 2300h their CRC-32s; 2400h diagnostics. Statusword bits beyond
the state: 10 target reached (enabled and settled), 11 internal limit (the last setpoint was beyond the stroke),
13 following error (in FAULT after one), 14 the e-stop input is pressed. Leaving NMT service (STOPPED, a reset)
disables the machine first.
"""

from __future__ import annotations

import struct
import zlib
from pathlib import Path

import numpy as np
from canopen.sdo import SdoAbortedError

from hilcal.protocols.canopen import HEXAPOD_CONTROLLER_EDS
from hilcal.protocols.compensation import FORMAT, LEG_FIELDS
from hilcal.protocols.controller_states import Command as ModelCommand
from hilcal.protocols.controller_states import ControllerState, FaultCode, RefusalReason
from sim_devices.canopen import cia402
from sim_devices.canopen.cia402 import State, Statusword
from sim_devices.canopen.model import CanopenController, ParameterRefused
from sim_devices.canopen.node import FrameSink, NmtState, SimulatedNode
from sim_devices.canopen.nvram import Category, Nvram
from sim_devices.canopen.pdo import SdoAbort
from sim_devices.controller.state_machine import ControllerSnapshot

N_LEGS = 6
SNAPSHOT_MAX_AGE_S = 0.005
"""Reads within this long share one snapshot of the model (a TPDO's six lengths are one instant)."""
FAULT_POLL_S = 0.01
"""The node looks for a model fault this often (real time) to send its EMCY without a host asking."""

EMCY_OF_FAULT: dict[FaultCode, tuple[int, int]] = {
    FaultCode.FOLLOWING_ERROR: (0x8611, 0x20),
    FaultCode.HYDRAULIC_PRESSURE: (0xFF02, 0x80),
    FaultCode.LEG_LIMIT: (0xFF03, 0x80),
    FaultCode.DRIVE: (0x5000, 0x00),
    FaultCode.ENCODER: (0x7300, 0x20),
    FaultCode.INTERNAL: (0x6000, 0x00),
    FaultCode.ESTOP_INPUT: (0x9000, 0x00),
    FaultCode.ESTOP_REQUEST: (0x9000, 0x00),
}
"""EMCY error code (CiA 301 table 21 classes, CiA 402 8611h following error, FFxxh manufacturer-specific) and the
error register bits (5: device profile, 7: manufacturer) of each model fault."""

ABORT_OF_REASON = {"state": SdoAbort.DEVICE_STATE, "read_only": SdoAbort.WRITE_READ_ONLY,
                   "range": SdoAbort.VALUE_RANGE, "unsupported": SdoAbort.CANNOT_STORE}
"""SDO abort code (CiA 301 table 22) of each ParameterRefused reason."""


def emcy_of(fault: FaultCode) -> tuple[int, int]:
    return EMCY_OF_FAULT.get(fault, (0x1000, 0x00))


def geometry_crc(values: np.ndarray) -> int:
    """CRC-32/ISO-HDLC of the 42 values as REAL32 little-endian (2300h sub 1 and 3)."""
    return zlib.crc32(struct.pack(f"<{len(values)}f", *values.tolist())) & 0xFFFFFFFF


def compensation_crc(block: dict) -> int:
    """CRC-32/ISO-HDLC of format, points, reference temperature, then per leg its terms and table (2300h sub 2, 4)."""
    points = int(block["table_points"])
    data = struct.pack("<HHf", FORMAT, points, block["reference_temperature_c"])
    for leg in range(N_LEGS):
        data += struct.pack("<7f", *(block[name][leg] for name in LEG_FIELDS))
        data += struct.pack(f"<{points}f", *block["table_mm"][leg])
    return zlib.crc32(data) & 0xFFFFFFFF


def refuse(err: ParameterRefused) -> SdoAbortedError:
    return SdoAbortedError(ABORT_OF_REASON[err.reason])


class HexapodNode(SimulatedNode):
    """The HX-6 on a frame sink (see the module docstring)."""

    def __init__(self, node_id: int, model: CanopenController, sink: FrameSink, nvram: Nvram,
                 eds_path: Path = HEXAPOD_CONTROLLER_EDS) -> None:
        super().__init__(node_id, eds_path, sink, nvram)
        self.model = model
        self.state = State.SWITCH_ON_DISABLED
        self._controlword = 0
        self._applied_tag = 0
        self._result = RefusalReason.ACCEPTED
        self._limit_active = False
        self._fault_code = 0
        self._snap: tuple[float, ControllerSnapshot] | None = None
        self._next_fault_poll = 0.0
        r, w = self.readers, self.writers
        r[0x1018] = lambda sub: model.config.serial_number if sub == 4 else None
        r[0x603F] = lambda _: self._fault_code
        r[0x6041] = lambda _: self.statusword()
        w[0x6040] = self._write_controlword
        w[0x2001] = self._write_apply
        r[0x2002] = lambda _: self._applied_tag
        r[0x2003] = lambda _: int(self._result)
        r[0x2010] = lambda sub: float(self.snapshot().lengths_mm[sub - 1]) if sub else None
        r[0x2011] = lambda _: sum(1 << k for k, ok in enumerate(self.snapshot().in_position) if ok)
        r[0x2012] = lambda sub: float(model.leg_forces_reading()[sub - 1]) if sub else None
        r[0x2013] = lambda _: float(model.temperature_reading())
        r[0x2020] = lambda sub: float(model.leg_limits_mm()[sub - 1]) if sub else None
        for k in range(N_LEGS):
            r[0x2100 + k] = self._geometry_reader(3 * k)
            w[0x2100 + k] = self._geometry_writer(3 * k)
            r[0x2110 + k] = self._geometry_reader(18 + 3 * k)
            w[0x2110 + k] = self._geometry_writer(18 + 3 * k)
            r[0x2210 + k] = self._table_reader(k)
            w[0x2210 + k] = self._table_writer(k)
        r[0x2120] = self._geometry_reader(36)
        w[0x2120] = self._geometry_writer(36)
        r[0x2200] = self._read_header
        w[0x2200] = self._write_header
        for k, name in enumerate(LEG_FIELDS):
            r[0x2201 + k] = self._term_reader(name)
            w[0x2201 + k] = self._term_writer(name)
        r[0x2300] = self._read_checksums
        r[0x2400] = self._read_diagnostics

    # ------------------------------------------------------------------ model state

    def snapshot(self) -> ControllerSnapshot:
        now = self.now
        if self._snap is None or now - self._snap[0] > SNAPSHOT_MAX_AGE_S or now < self._snap[0]:
            self._snap = (now, self.model.snapshot())
        return self._snap[1]

    def _fresh_snapshot(self) -> ControllerSnapshot:
        self._snap = None
        return self.snapshot()

    def _follow_model(self, snap: ControllerSnapshot) -> None:
        """A model fault or e-stop puts the device in FAULT with its EMCY; a model disabled under an enabled device
        (a fault reset elsewhere) takes it to SWITCH ON DISABLED."""
        if snap.state in (ControllerState.FAULT, ControllerState.ESTOP):
            if self.state is not State.FAULT:
                self.state = State.FAULT
                code, bits = emcy_of(snap.fault)
                self._fault_code = code
                self.raise_error(code, bits, bytes([int(snap.fault)]))
        elif self.state is State.OPERATION_ENABLED and snap.state is ControllerState.DISABLED:
            self.state = State.SWITCH_ON_DISABLED

    def statusword(self) -> int:
        snap = self.snapshot()
        self._follow_model(snap)
        extra = 0
        if self.state is State.OPERATION_ENABLED and snap.state in (ControllerState.ENABLED,
                                                                    ControllerState.IN_POSITION):
            extra |= Statusword.TARGET_REACHED
        if self._limit_active:
            extra |= Statusword.INTERNAL_LIMIT_ACTIVE
        if self.state is State.FAULT and snap.fault is FaultCode.FOLLOWING_ERROR:
            extra |= Statusword.FOLLOWING_ERROR
        if snap.estop_input:
            extra |= Statusword.MANUFACTURER_14
        return cia402.statusword(self.state, extra)

    def device_tick(self, now: float) -> None:
        if now >= self._next_fault_poll:
            self._next_fault_poll = now + FAULT_POLL_S
            self._follow_model(self.snapshot())

    # ------------------------------------------------------------------ device control

    def _write_controlword(self, sub: int, data: bytes) -> None:
        word = int.from_bytes(data, "little")
        command = cia402.decode(word, self._controlword)
        self._controlword = word
        self._follow_model(self._fresh_snapshot())
        old = self.state
        new = cia402.transition(old, command)
        if old is State.FAULT and new is not State.FAULT:
            stopped = self.snapshot().state in (ControllerState.FAULT, ControllerState.ESTOP)
            if stopped and self.model.command(ModelCommand.FAULT_RESET) is not RefusalReason.ACCEPTED:
                return
            self._fault_code = 0
            self.clear_errors()
        if new is State.OPERATION_ENABLED and old is not State.OPERATION_ENABLED:
            if self.model.command(ModelCommand.ENABLE) is not RefusalReason.ACCEPTED:
                self._follow_model(self._fresh_snapshot())
                return
            self._limit_active = False
        elif old is State.OPERATION_ENABLED and new is not State.OPERATION_ENABLED:
            self.model.command(ModelCommand.STOP)
            self.model.command(ModelCommand.DISABLE)
        elif new is State.OPERATION_ENABLED and word & cia402.Controlword.HALT:
            self.model.command(ModelCommand.STOP)
        self.state = new
        self._snap = None

    def _write_apply(self, sub: int, data: bytes) -> None:
        tag = int.from_bytes(data, "little")
        snap = self._fresh_snapshot()
        self._follow_model(snap)
        if self.state is not State.OPERATION_ENABLED:
            self._result = {State.FAULT: RefusalReason.FAULT_ACTIVE}.get(self.state, RefusalReason.WRONG_STATE)
            if snap.state is ControllerState.ESTOP:
                self._result = RefusalReason.ESTOP_ACTIVE
            raise SdoAbortedError(SdoAbort.DEVICE_STATE)
        targets = [float(self.value(0x2000, leg)) for leg in range(1, N_LEGS + 1)]
        self._result = self.model.set_setpoint(targets, tag)
        self._snap = None
        if self._result is RefusalReason.SETPOINT_OUT_OF_LIMITS:
            self._limit_active = True
            raise SdoAbortedError(SdoAbort.VALUE_RANGE)
        if self._result is not RefusalReason.ACCEPTED:
            raise SdoAbortedError(SdoAbort.DEVICE_STATE)
        self._limit_active = False
        self._applied_tag = tag

    def nmt_changed(self, old: NmtState, new: NmtState) -> None:
        if new in (NmtState.STOPPED, NmtState.INITIALISING) and self.state is State.OPERATION_ENABLED:
            self.model.command(ModelCommand.STOP)
            self.model.command(ModelCommand.DISABLE)
            self.state = State.SWITCH_ON_DISABLED
            self._snap = None

    def reset_application(self) -> None:
        self.model.load_stored()
        self.state = State.SWITCH_ON_DISABLED
        self._controlword = 0
        self._applied_tag = 0
        self._result = RefusalReason.ACCEPTED
        self._limit_active = False
        self._fault_code = 0
        self._snap = None

    def store(self, categories: tuple[Category, ...]) -> None:
        if Category.MANUFACTURER in categories:
            try:
                self.model.store()
            except ParameterRefused as err:
                raise refuse(err) from None

    def restore_defaults(self, categories: tuple[Category, ...]) -> None:
        if Category.MANUFACTURER in categories:
            self.model.restore_factory()

    # ------------------------------------------------------------------ parameters

    def _geometry_reader(self, first: int):
        return lambda sub: float(self.model.geometry()[first + sub - 1]) if sub else None

    def _geometry_writer(self, first: int):
        def write(sub: int, data: bytes) -> None:
            if sub == 0:
                raise SdoAbortedError(SdoAbort.WRITE_READ_ONLY)
            try:
                self.model.write_geometry(first + sub - 1, struct.unpack("<f", data)[0])
            except ParameterRefused as err:
                raise refuse(err) from None
        return write

    def _term_reader(self, name: str):
        return lambda sub: float(self.model.block()[name][sub - 1]) if sub else None

    def _term_writer(self, name: str):
        def write(sub: int, data: bytes) -> None:
            try:
                self.model.write_term(name, sub - 1, struct.unpack("<f", data)[0])
            except ParameterRefused as err:
                raise refuse(err) from None
        return write

    def _read_header(self, sub: int) -> float | int | None:
        block = self.model.block()
        return {1: FORMAT, 2: int(block["table_points"]), 3: float(block["reference_temperature_c"])}.get(sub)

    def _write_header(self, sub: int, data: bytes) -> None:
        try:
            if sub == 2:
                self.model.write_table_points(int.from_bytes(data, "little"))
            elif sub == 3:
                self.model.write_reference_temperature(struct.unpack("<f", data)[0])
        except ParameterRefused as err:
            raise refuse(err) from None

    def _table_reader(self, leg: int):
        def read(sub: int) -> bytes:
            table = self.model.block()["table_mm"][leg]
            return struct.pack(f"<{len(table)}f", *table)
        return read

    def _table_writer(self, leg: int):
        def write(sub: int, data: bytes) -> None:
            points = int(self.model.block()["table_points"])
            if len(data) != 4 * points:
                raise SdoAbortedError(SdoAbort.LENGTH_MISMATCH)
            try:
                self.model.write_table(leg, struct.unpack(f"<{points}f", data))
            except ParameterRefused as err:
                raise refuse(err) from None
        return write

    def _read_checksums(self, sub: int) -> int | None:
        if sub == 1:
            return geometry_crc(self.model.geometry("live"))
        if sub == 2:
            return compensation_crc(self.model.block("live"))
        if sub == 3:
            return geometry_crc(self.model.geometry("saved"))
        if sub == 4:
            return compensation_crc(self.model.block("saved"))
        return self.model.store_count if sub == 5 else None

    def _read_diagnostics(self, sub: int) -> int | None:
        snap = self.snapshot()
        values = {1: int(snap.state), 2: int(snap.fault), 3: int(snap.estop_input), 4: snap.fault_events & 0xFFFF}
        return values.get(sub)
