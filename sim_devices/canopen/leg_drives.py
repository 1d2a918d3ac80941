"""Six LD-1 leg drives (``cia402_leg_drive.eds``): one CiA 402 servo drive per leg of an electric hexapod, each its
own node, in profile position mode, sharing the controller model whose legs are their axes.

Units (as the EDS says): position 1 µm (6064h = the leg length: home offset 607Ch + stroke; 607Ah the target leg
length), velocity µm/s; 6063h in encoder increments (1048576 per motor revolution, 1:1 gear, 5000 µm feed per
revolution). Each drive runs its own CiA 402 state machine (``cia402``); the model is enabled while any drive is in
OPERATION ENABLED, and a leg whose drive is not enabled holds where it is. Profile position (CiA 402-2, 6060h = 1):
the 0 -> 1 edge of controlword bit 4 takes 607Ah (relative with bit 6) as the new target at once (as with bit 5 set;
no set-point buffer) and sets statusword bit 12 until bit 4 falls; a target outside 607Dh is not taken (bit 11
set until the next one). Bit 10 (target reached) is set while the leg is within the model's in-position tolerance
of its target. The profile velocity and accelerations are kept but the legs move at the model's ``leg_speed_mm_s``
(one speed for the machine); 60F4h reads 0 (the model has no following error before its limit). A model fault puts
every drive in FAULT with its EMCY; each drive's fault reset takes it out. The home offset is the model's live leg
offset l0 (µm, rounded), changed at once and only while the machine is disabled (abort 08000022h); a drive's 1010h
stores its own leg offset, 1011h restores the robot file's at its next reset.
"""

from __future__ import annotations

import numpy as np
from canopen.sdo import SdoAbortedError

from hilcal.protocols.canopen import CIA402_LEG_DRIVE_EDS
from hilcal.protocols.controller_states import Command as ModelCommand
from hilcal.protocols.controller_states import ControllerState, FaultCode, RefusalReason
from hilcal.protocols.registers import L0_INDEX
from sim_devices.canopen import cia402
from sim_devices.canopen.cia402 import Controlword, State, Statusword
from sim_devices.canopen.hexapod_node import emcy_of, refuse
from sim_devices.canopen.model import CanopenController, ParameterRefused
from sim_devices.canopen.node import FrameSink, NmtState, SimulatedNode
from sim_devices.canopen.nvram import Category, Nvram
from sim_devices.canopen.pdo import SdoAbort
from sim_devices.controller.state_machine import ControllerSnapshot

UM_PER_MM = 1000
INCREMENTS_PER_REV = 1048576
FEED_UM_PER_REV = 5000
PROFILE_POSITION = 1
QUICK_STOP_OPTION = 2
SNAPSHOT_MAX_AGE_S = 0.005
FAULT_POLL_S = 0.01


def um(mm: float) -> int:
    return round(mm * UM_PER_MM)


class LegDriveGroup:
    """The six drives and what they share: the model, one snapshot per instant, the set-point vector."""

    def __init__(self, model: CanopenController, node_ids: list[int], sink: FrameSink, nvram: Nvram) -> None:
        self.model = model
        self.drives = [LegDrive(self, leg, node_id, sink, nvram) for leg, node_id in enumerate(node_ids)]
        self._snap: tuple[float, ControllerSnapshot] | None = None

    def snapshot(self, now: float, fresh: bool = False) -> ControllerSnapshot:
        if fresh or self._snap is None or now - self._snap[0] > SNAPSHOT_MAX_AGE_S or now < self._snap[0]:
            self._snap = (now, self.model.snapshot())
        return self._snap[1]

    def forget(self) -> None:
        self._snap = None

    def enabled(self) -> list[LegDrive]:
        return [d for d in self.drives if d.state is State.OPERATION_ENABLED]

    def enable(self) -> bool:
        """A drive enters OPERATION ENABLED: the machine is enabled unless it already is."""
        if self.model.snapshot().state is ControllerState.DISABLED:
            return self.model.command(ModelCommand.ENABLE) is RefusalReason.ACCEPTED
        return True

    def release(self, drive: LegDrive) -> None:
        """A drive leaves OPERATION ENABLED: the machine is disabled if it was the last, else its leg holds."""
        drive.target_um = None
        others = [d for d in self.enabled() if d is not drive]
        if not others:
            self.model.command(ModelCommand.STOP)
            self.model.command(ModelCommand.DISABLE)
        else:
            self.move()
        self.forget()

    def move(self) -> RefusalReason:
        """Send the machine to every enabled drive's target; the other legs hold their lengths."""
        lengths = self.model.snapshot().lengths_mm.astype(float)
        for d in self.drives:
            if d.target_um is not None and d.state is State.OPERATION_ENABLED:
                lengths[d.leg] = d.target_um / UM_PER_MM
        self.forget()
        return self.model.set_setpoint(lengths)


class LegDrive(SimulatedNode):
    """One LD-1 drive (see the module docstring)."""

    def __init__(self, group: LegDriveGroup, leg: int, node_id: int, sink: FrameSink, nvram: Nvram) -> None:
        super().__init__(node_id, CIA402_LEG_DRIVE_EDS, sink, nvram)
        self.group = group
        self.leg = leg
        self.state = State.SWITCH_ON_DISABLED
        self.target_um: int | None = None
        self._controlword = 0
        self._ack = False
        self._limit_active = False
        self._fault_code = 0
        self._next_fault_poll = 0.0
        model = group.model
        r, w = self.readers, self.writers
        r[0x1018] = lambda sub: (model.config.serial_number + leg + 1) & 0xFFFFFFFF if sub == 4 else None
        r[0x603F] = lambda _: self._fault_code
        r[0x6041] = lambda _: self.statusword()
        w[0x6040] = self._write_controlword
        w[0x605A] = self._write_quick_stop_option
        w[0x6060] = self._write_mode
        r[0x6061] = lambda _: int(self.value(0x6060))
        r[0x6062] = lambda _: self.target_um if self.target_um is not None else um(self._length_mm())
        r[0x6063] = lambda _: round((self._length_mm() - self._l0_mm()) * UM_PER_MM * INCREMENTS_PER_REV
                                    / FEED_UM_PER_REV)
        r[0x6064] = lambda _: um(self._length_mm())
        r[0x606C] = lambda _: self._velocity_um_s()
        r[0x607C] = lambda _: um(self._l0_mm())
        w[0x607C] = self._write_home_offset
        r[0x607D] = lambda sub: um(model.leg_limits_mm()[sub - 1]) if sub else None
        r[0x60F4] = lambda _: 0

    # ------------------------------------------------------------------ readings

    def _snapshot(self, fresh: bool = False) -> ControllerSnapshot:
        return self.group.snapshot(self.now, fresh)

    def _length_mm(self) -> float:
        return float(self._snapshot().lengths_mm[self.leg])

    def _l0_mm(self) -> float:
        return float(self.group.model.geometry()[L0_INDEX + self.leg])

    def _reached(self, snap: ControllerSnapshot) -> bool:
        if snap.state is ControllerState.ENABLED:
            return True
        return snap.state in (ControllerState.MOVING, ControllerState.IN_POSITION) and snap.in_position[self.leg]

    def _velocity_um_s(self) -> int:
        snap = self._snapshot()
        if self.state is not State.OPERATION_ENABLED or self.target_um is None or self._reached(snap):
            return 0
        speed = self.group.model.config.leg_speed_mm_s * UM_PER_MM
        return int(np.sign(self.target_um - um(self._length_mm())) * speed)

    def _follow_model(self, snap: ControllerSnapshot) -> None:
        if snap.state in (ControllerState.FAULT, ControllerState.ESTOP):
            if self.state is not State.FAULT:
                self.state = State.FAULT
                self.target_um = None
                code, bits = emcy_of(snap.fault)
                self._fault_code = code
                self.raise_error(code, bits, bytes([int(snap.fault)]))
        elif self.state is State.OPERATION_ENABLED and snap.state is ControllerState.DISABLED:
            self.state = State.SWITCH_ON_DISABLED
            self.target_um = None

    def statusword(self) -> int:
        snap = self._snapshot()
        self._follow_model(snap)
        extra = 0
        if self.state is State.OPERATION_ENABLED and self._reached(snap):
            extra |= Statusword.TARGET_REACHED
        if self._limit_active:
            extra |= Statusword.INTERNAL_LIMIT_ACTIVE
        if self._ack:
            extra |= Statusword.SET_POINT_ACKNOWLEDGE
        if self.state is State.FAULT and snap.fault is FaultCode.FOLLOWING_ERROR:
            extra |= Statusword.FOLLOWING_ERROR
        if snap.estop_input:
            extra |= Statusword.MANUFACTURER_14
        return cia402.statusword(self.state, extra)

    def device_tick(self, now: float) -> None:
        if now >= self._next_fault_poll:
            self._next_fault_poll = now + FAULT_POLL_S
            self._follow_model(self._snapshot())

    # ------------------------------------------------------------------ device control

    def _write_controlword(self, sub: int, data: bytes) -> None:
        word = int.from_bytes(data, "little")
        previous, self._controlword = self._controlword, word
        self._follow_model(self._snapshot(fresh=True))
        old = self.state
        new = cia402.transition(old, cia402.decode(word, previous))
        if old is State.FAULT and new is not State.FAULT:
            stopped = self._snapshot(fresh=True).state in (ControllerState.FAULT, ControllerState.ESTOP)
            if stopped and self.group.model.command(ModelCommand.FAULT_RESET) is not RefusalReason.ACCEPTED:
                return
            self._fault_code = 0
            self.clear_errors()
        if new is State.OPERATION_ENABLED and old is not State.OPERATION_ENABLED:
            if not self.group.enable():
                self._follow_model(self._snapshot(fresh=True))
                return
            self._limit_active = False
        elif old is State.OPERATION_ENABLED and new is not State.OPERATION_ENABLED:
            self.state = new
            self.group.release(self)
        self.state = new
        if not word & Controlword.NEW_SET_POINT:
            self._ack = False
        elif not previous & Controlword.NEW_SET_POINT and new is State.OPERATION_ENABLED:
            self._new_set_point(word)
        self.group.forget()

    def _new_set_point(self, word: int) -> None:
        if int(self.value(0x6060)) != PROFILE_POSITION or word & Controlword.HALT:
            return
        self._ack = True
        target = int(self.value(0x607A))
        if word & Controlword.ABS_REL:
            base = self.target_um if self.target_um is not None else um(self._length_mm())
            target += base
        lo, hi = (um(v) for v in self.group.model.leg_limits_mm())
        if not lo <= target <= hi:
            self._limit_active = True
            return
        previous, self.target_um = self.target_um, target
        if self.group.move() is RefusalReason.ACCEPTED:
            self._limit_active = False
        else:
            self.target_um = previous
            self._limit_active = True

    def _write_quick_stop_option(self, sub: int, data: bytes) -> None:
        if int.from_bytes(data, "little", signed=True) != QUICK_STOP_OPTION:
            raise SdoAbortedError(SdoAbort.VALUE_RANGE)

    def _write_mode(self, sub: int, data: bytes) -> None:
        if int.from_bytes(data, "little", signed=True) not in (0, PROFILE_POSITION):
            raise SdoAbortedError(SdoAbort.VALUE_RANGE)

    def _write_home_offset(self, sub: int, data: bytes) -> None:
        try:
            self.group.model.write_geometry(L0_INDEX + self.leg, int.from_bytes(data, "little", signed=True)
                                            / UM_PER_MM)
        except ParameterRefused as err:
            raise refuse(err) from None
        self.group.forget()

    # ------------------------------------------------------------------ NMT, store

    def nmt_changed(self, old: NmtState, new: NmtState) -> None:
        if new in (NmtState.STOPPED, NmtState.INITIALISING) and self.state is State.OPERATION_ENABLED:
            self.state = State.SWITCH_ON_DISABLED
            self.group.release(self)

    def reset_application(self) -> None:
        self.group.model.load_stored([L0_INDEX + self.leg])
        self.state = State.SWITCH_ON_DISABLED
        self.target_um = None
        self._controlword = 0
        self._ack = self._limit_active = False
        self._fault_code = 0
        self.group.forget()

    def store(self, categories: tuple[Category, ...]) -> None:
        if Category.APPLICATION in categories:
            try:
                self.group.model.store([L0_INDEX + self.leg])
            except ParameterRefused as err:
                raise refuse(err) from None

    def restore_defaults(self, categories: tuple[Category, ...]) -> None:
        if Category.APPLICATION in categories:
            self.group.model.restore_factory([L0_INDEX + self.leg])
