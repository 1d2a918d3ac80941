"""Motion of a CANopen controller: the device control of CiA 402 (or the mapping's), leg setpoints and actual lengths
by SDO through the station's mapping, the heartbeat as the link's liveness, emergencies named in faults.

Enable walks the CiA 402 state machine (CiA 402-2 §8.4: shutdown, switch on, enable operation, each acknowledged by
the statusword within ``ack_timeout_s``) on every device-control node (a device without one, ``power_states = false``,
is enabled by the run alone: it follows setpoints whenever it is not in fault); disable is "shutdown", stop raises
the halt bit, estop sends "quick stop" to every node even when the link looks lost (a device with no halt or no
quick stop, mapped ``"none"``, is refused with words and nothing written), fault reset the 0 -> 1 edge of bit 7.
``move_legs`` checks the leg limits before anything is sent, refuses while a node's heartbeat is missing, writes the
six setpoints once (never again blind: a lost answer is a CommandTimeout), applies them (the mapping's apply object,
or the profile-position handshake) and waits, bounded, until every node reports target reached with the actual
lengths within the tolerance. A fault names the emergency codes and error register the nodes sent.
"""

from __future__ import annotations

import itertools
import time
from collections.abc import Sequence

import numpy as np
import structlog

from drivers.controller.base import (
    CommandRefused,
    CommandTimeout,
    ControllerError,
    ControllerFault,
    ControllerInterface,
    ControllerLost,
    EStopActive,
    Feedback,
    LimitViolation,
    MotionAborted,
    MotionTimeout,
    PositionMismatch,
    check_leg_limits,
    legs_not_following,
    not_following_text,
)
from drivers.controller.canopen_link import CanopenLink, SdoFailure
from drivers.controller.canopen_mapping import drive_state
from drivers.controller.canopen_resolved import Resolved
from hilcal.protocols.controller_states import MOTION_STATES, ControllerState, FaultCode, RefusalReason
from hilcal.robot import Robot

log = structlog.get_logger(__name__)

POLL_S = 0.005
REFUSALS = {0x08000022: RefusalReason.WRONG_STATE, 0x06090030: RefusalReason.SETPOINT_OUT_OF_LIMITS,
            0x06090031: RefusalReason.SETPOINT_OUT_OF_LIMITS, 0x06090032: RefusalReason.SETPOINT_OUT_OF_LIMITS}
"""SDO aborts of a setpoint or command that say why the device refused it (CiA 301 table 22)."""


def fault_code(emcy: int) -> FaultCode:
    """The controller fault an emergency code means (CiA 402-2 / CiA 301 classes); INTERNAL when none fits."""
    if emcy == 0x8611:
        return FaultCode.FOLLOWING_ERROR
    if emcy == 0x8612:
        return FaultCode.LEG_LIMIT
    if emcy & 0xFF00 == 0x7300:
        return FaultCode.ENCODER
    if emcy & 0xF000 == 0x9000:
        return FaultCode.ESTOP_INPUT
    if emcy & 0xF000 in (0x2000, 0x3000, 0x5000):
        return FaultCode.DRIVE
    return FaultCode.INTERNAL


class CanopenController(ControllerInterface):
    """Leg motion of a CANopen controller through a resolved mapping (see the module docstring)."""

    def __init__(self, link: CanopenLink, resolved: Resolved, robot: Robot, *, ack_timeout_s: float = 0.5,
                 position_tolerance_mm: float = 0.01) -> None:
        self.link = link
        self.map = resolved
        self.robot = robot
        self.ack_timeout_s = ack_timeout_s
        self.position_tolerance_mm = position_tolerance_mm
        self.control = resolved.mapping.device_control
        self.vendor_codes = resolved.mapping.vendor_codes()
        self._tags = itertools.count(1)
        self._reached = False
        self._halted = False
        self._enabled = False
        """A device without power states (``power_states = false``): whether the run has enabled it."""
        self.last_fault_event: tuple[FaultCode, ControllerState] | None = None

    # ------------------------------------------------------------------ liveness

    @property
    def controller_alive(self) -> bool:
        return self.link.alive()

    @property
    def heartbeat_age_s(self) -> float | None:
        return self.link.heartbeat_age_s()

    @property
    def estop_input(self) -> bool:
        """No e-stop input object is mapped: an e-stop shows as a fault with its emergency code."""
        return False

    def _require_alive(self) -> None:
        if not self.link.alive():
            silent = self.link.silent_nodes()
            raise ControllerLost(f"controller lost: no heartbeat from node(s) {silent} within "
                                 f"{self.link.heartbeat_timeout_s:.3f} s; nothing is sent until heartbeats resume")

    def wait_for_heartbeat(self, timeout_s: float = 1.0) -> Feedback:
        if not self.link.wait_alive(timeout_s):
            raise ControllerLost(f"no heartbeat from node(s) {self.link.silent_nodes()} within {timeout_s} s")
        return self.feedback()

    # ------------------------------------------------------------------ reads

    def _sdo(self, call, *args):
        """An SDO request in a motion context: a lost answer is a lost link or a timeout, an abort a refusal."""
        try:
            return call(*args)
        except SdoFailure as err:
            if err.code is None:
                if not self.link.alive():
                    raise ControllerLost(str(err)) from None
                raise CommandTimeout(str(err)) from None
            raise CommandRefused(str(err), REFUSALS.get(err.code, RefusalReason.WRONG_STATE), None,
                                 "controller") from None

    def _words(self) -> dict[int, int]:
        return {n: int(self._sdo(self.link.read, slot)) for n, slot in self.map.statusword.items()}

    def _lengths(self) -> np.ndarray:
        return np.array([s.value(self._sdo(self.link.read, s)) for s in self.map.actual])

    def _combine(self, words: dict[int, int]) -> ControllerState:
        states = {drive_state(w, self.control) for w in words.values()}
        if states & {"fault", "fault_reaction"}:
            return ControllerState.FAULT
        if "quick_stop" in states:
            return ControllerState.ESTOP
        enabled = self._enabled if not self.control.power_states else states == {"enabled"}
        if not enabled:
            return ControllerState.DISABLED
        reached = all(w >> self.control.target_reached_bit & 1 for w in words.values())
        if not reached:
            return ControllerState.MOVING
        return ControllerState.IN_POSITION if self._reached else ControllerState.ENABLED

    def _fault(self, since_s: float = 0.0) -> tuple[FaultCode, str]:
        emergencies = [e for e in self.link.emergencies_since(since_s) if e.code != 0]
        if not emergencies:
            return FaultCode.INTERNAL, "no emergency message received"
        last = emergencies[-1]
        return fault_code(last.code), "; ".join(e.text(self.vendor_codes) for e in emergencies[-3:])

    @property
    def state(self) -> ControllerState:
        self._require_alive()
        state = self._combine(self._words())
        if state in (ControllerState.FAULT, ControllerState.ESTOP):
            self.last_fault_event = (self._fault()[0], state)
        return state

    def feedback(self) -> Feedback:
        self._require_alive()
        state = self._combine(self._words())
        fault = self._fault()[0] if state is ControllerState.FAULT else FaultCode.NONE
        return Feedback(self._lengths(), state, fault)

    # ------------------------------------------------------------------ device control

    def _control(self, value: int, nodes: Sequence[int] | None = None) -> None:
        for n in nodes or list(self.map.controlword):
            self._sdo(self.link.write, self.map.controlword[n], value)

    def _await(self, wanted: set[str], what: str) -> dict[int, int]:
        """Wait (ack_timeout_s) until every node's statusword codes one of ``wanted``."""
        deadline = time.monotonic() + self.ack_timeout_s
        while True:
            words = self._words()
            states = {n: drive_state(w, self.control) for n, w in words.items()}
            if all(s in wanted for s in states.values()):
                return words
            if time.monotonic() > deadline:
                text = ", ".join(f"node {n} {s} (0x{words[n]:04X})" for n, s in states.items())
                raise CommandTimeout(f"{what}: the device did not reach {sorted(wanted)} within "
                                     f"{self.ack_timeout_s} s: {text}")
            time.sleep(POLL_S)

    def _refuse_unless(self, allowed: set[ControllerState], command: str) -> ControllerState:
        state = self.state
        if state not in allowed:
            reason = {ControllerState.FAULT: RefusalReason.FAULT_ACTIVE,
                      ControllerState.ESTOP: RefusalReason.ESTOP_ACTIVE}.get(state, RefusalReason.WRONG_STATE)
            raise CommandRefused(f"{command} refused in state {state.name}: {reason.name} (not sent)", reason, state,
                                 "driver")
        return state

    def enable(self) -> None:
        """Shutdown, switch on, enable operation (CiA 402-2 transitions 2, 3, 4), each acknowledged; a device without
        power states is only checked to be out of fault."""
        self._refuse_unless({ControllerState.DISABLED}, "ENABLE")
        if self.control.operation_mode is not None:
            for n, (mode, display) in self.map.mode.items():
                self._sdo(self.link.write, mode, self.control.operation_mode)
                shown = int(self._sdo(self.link.read, display))
                if shown != self.control.operation_mode:
                    raise CommandRefused(f"node {n} shows mode of operation {shown}, not "
                                         f"{self.control.operation_mode}", RefusalReason.WRONG_STATE, None,
                                         "controller")
        c = self.control
        if not c.power_states:
            self._enabled, self._reached = True, False
            log.info("canopen_enabled", nodes=list(self.map.controlword), power_states=False)
            return
        self._control(c.shutdown)
        self._await({"ready", "switched_on", "enabled"}, "shutdown")
        self._control(c.switch_on)
        self._await({"switched_on", "enabled"}, "switch on")
        self._control(c.enable_operation)
        self._await({"enabled"}, "enable operation")
        self._reached = False
        log.info("canopen_enabled", nodes=list(self.map.controlword))

    def disable(self) -> None:
        """Shutdown from operation enabled (CiA 402-2 transition 8): the legs are no longer servoed."""
        self._refuse_unless(set(MOTION_STATES), "DISABLE")
        if not self.control.power_states:
            self._enabled = False
            log.info("canopen_disabled", power_states=False)
            return
        self._control(self.control.shutdown)
        self._await({"ready", "switch_on_disabled", "switched_on", "not_ready"}, "shutdown")
        log.info("canopen_disabled")

    def stop(self) -> None:
        """Halt where the legs are (controlword halt bit), staying enabled."""
        self._refuse_unless(set(MOTION_STATES), "STOP")
        if self.control.halt_bit is None:
            raise CommandRefused('the device has no halt over the bus (device_control.halt_bit = "none"): a move in '
                                 "progress runs to its end", RefusalReason.UNKNOWN_COMMAND, None, "driver")
        self._control(self.control.enable_operation | 1 << self.control.halt_bit)
        self._halted = True

    def fault_reset(self) -> None:
        """Fault reset: bit 7's 0 -> 1 edge (CiA 402-2 transition 15), then wait for switch on disabled."""
        state = self._refuse_unless({ControllerState.FAULT, ControllerState.ESTOP}, "FAULT_RESET")
        self._control(self.control.disable_voltage)
        self._control(self.control.fault_reset)
        self._await({"switch_on_disabled", "ready", "not_ready", "at_rest", "moving"}, "fault reset")
        self._control(self.control.disable_voltage)
        log.info("canopen_fault_reset", was=state.name)

    def estop(self) -> None:
        """Quick stop to every node, sent whatever the state or the link; waits (bounded) until none is enabled."""
        log.warning("canopen_estop_requested")
        if self.control.quick_stop is None:
            raise CommandRefused('the device has no quick stop over the bus (device_control.quick_stop = "none"): stop '
                                 "it with the machine's hardware e-stop", RefusalReason.UNKNOWN_COMMAND, None, "driver")
        failures = []
        for n, slot in self.map.controlword.items():
            try:
                self.link.write(slot, self.control.quick_stop)
            except SdoFailure as err:
                failures.append(f"node {n}: {err}")
        self._require_alive()
        if failures:
            raise CommandTimeout(f"quick stop not acknowledged: {'; '.join(failures)}")
        self._await({"quick_stop", "switch_on_disabled", "fault", "fault_reaction", "ready", "switched_on"},
                    "quick stop")

    # ------------------------------------------------------------------ motion

    def move_legs(self, lengths_mm: Sequence[float] | np.ndarray, timeout_s: float) -> np.ndarray:
        """Check, send once, apply, wait for target reached within the tolerance; the measured lengths (mm)."""
        target = check_leg_limits(self.robot, lengths_mm)
        try:
            raws = [s.raw(float(v)) for s, v in zip(self.map.setpoints, target, strict=True)]
        except ValueError as err:
            raise LimitViolation(f"{err}; nothing sent") from None
        self._refuse_unless(set(MOTION_STATES), "setpoint")
        before = self._lengths()
        started = time.monotonic()
        self._reached = False
        if self._halted:
            self._control(self.control.enable_operation)
            self._halted = False
        for slot, raw in zip(self.map.setpoints, raws, strict=True):
            self._sdo(self.link.write, slot, raw)
        self._apply()
        return self._wait(target, before, started, timeout_s)

    def _apply(self) -> None:
        sp = self.map.mapping.setpoints
        if self.map.apply is not None:
            value = next(self._tags) % 0xFFFF + 1 if sp.apply_counter else sp.apply_value
            self._sdo(self.link.write, self.map.apply, value)
            if self.map.apply_result is not None:
                result = int(self._sdo(self.link.read, self.map.apply_result))
                if result != 0:
                    meaning = sp.apply_results.get(result, "refused")
                    raise CommandRefused(f"the controller refused the setpoints: {self.map.apply_result} = {result} "
                                         f"({meaning})", RefusalReason.SETPOINT_OUT_OF_LIMITS if "limit" in meaning
                                         else RefusalReason.WRONG_STATE, None, "controller")
        if sp.new_setpoint_bit is not None:
            c = self.control
            word = c.enable_operation | 1 << sp.new_setpoint_bit
            if sp.change_immediately_bit is not None:
                word |= 1 << sp.change_immediately_bit
            self._control(word)
            if sp.ack_bit is not None:
                deadline = time.monotonic() + self.ack_timeout_s
                while not all(w >> sp.ack_bit & 1 for w in self._words().values()):
                    if time.monotonic() > deadline:
                        raise CommandTimeout(f"no set-point acknowledge (statusword bit {sp.ack_bit}) within "
                                             f"{self.ack_timeout_s} s; the setpoint may or may not have been taken")
                    time.sleep(POLL_S)
            self._control(c.enable_operation)

    def _wait(self, target: np.ndarray, before: np.ndarray, started: float, timeout_s: float) -> np.ndarray:
        lowest, highest = before.copy(), before.copy()
        deadline = started + timeout_s
        settled_polls = 0
        lengths = before
        while True:
            self._require_alive()
            words = self._words()
            lengths = self._lengths()
            lowest, highest = np.minimum(lowest, lengths), np.maximum(highest, lengths)
            state = self._combine(words)
            if state in (ControllerState.FAULT, ControllerState.ESTOP):
                code, text = self._fault(started)
                self.last_fault_event = (code, state)
                legs = legs_not_following(before, lowest, highest, target)
                stuck = f"; {not_following_text(legs, lengths, target, self.robot.leg_limits)}" if legs else ""
                error = EStopActive if code is FaultCode.ESTOP_INPUT else ControllerFault
                raise error(f"controller fault during the move: {text}{stuck}", state, code, legs)
            if state is ControllerState.DISABLED:
                raise MotionAborted("the move ended with the drive(s) no longer enabled, without reaching the target")
            error_mm = float(np.max(np.abs(lengths - target)))
            if state is ControllerState.ENABLED or state is ControllerState.IN_POSITION:
                if error_mm <= self.position_tolerance_mm:
                    self._reached = True
                    return lengths
                settled_polls += 1
                if settled_polls > 20 and time.monotonic() - started > 0.2:
                    raise PositionMismatch(f"target reached reported but the actual lengths differ from the "
                                           f"setpoint by up to {error_mm:.4f} mm (tolerance "
                                           f"{self.position_tolerance_mm} mm)")
            else:
                settled_polls = 0
            if time.monotonic() > deadline:
                break
            time.sleep(POLL_S)
        if self.control.halt_bit is None:
            halted = "no halt sent: the device has none"
        else:
            try:
                self.stop()
                halted = "halt sent"
            except Exception as err:
                log.warning("stop_after_timeout_failed", error=str(err))
                halted = f"the halt failed: {err}"
        legs = legs_not_following(before, lowest, highest, target)
        stuck = f": {not_following_text(legs, lengths, target, self.robot.leg_limits)}" if legs else ""
        raise MotionTimeout(f"legs not in position within {timeout_s} s{self._limits_text()}; {halted}{stuck}")

    def _limits_text(self) -> str:
        """Where the mapping has a limit bit: the nodes that show their internal limit active (else nothing)."""
        bit = self.control.limit_bit
        if bit is None:
            return ""
        try:
            active = [n for n, word in self._words().items() if word >> bit & 1]
        except ControllerError:  # the reason the move failed may also keep this read from answering
            return ""
        return f" (internal limit active on node {', '.join(map(str, active))})" if active else ""

    def close(self) -> None:
        self.link.close()
