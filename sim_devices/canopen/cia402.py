"""The CiA 402 device control state machine as the simulated devices run it: controlword in, statusword out.

Written from CiA 402-2 (state machine, controlword and statusword): the eight states, the device control
commands decoded from controlword bits 0-3 and 7 (fault reset on the 0 -> 1 edge of bit 7), the transitions each
command makes from each state, and the state bits 0-3, 5 and 6 of the statusword. Pure: the device adapters
(``hexapod_node``, ``leg_drives``) decide what a transition does to the machine and add the other statusword bits.
Quick stop follows option code 2 (slow down on the quick stop ramp, then SWITCH ON DISABLED): the simulated
machine stops at once, so QUICK STOP ACTIVE is left in the same step.
"""

from __future__ import annotations

from enum import Enum, IntEnum


class State(Enum):
    """CiA 402 device states."""

    NOT_READY_TO_SWITCH_ON = "NOT READY TO SWITCH ON"
    SWITCH_ON_DISABLED = "SWITCH ON DISABLED"
    READY_TO_SWITCH_ON = "READY TO SWITCH ON"
    SWITCHED_ON = "SWITCHED ON"
    OPERATION_ENABLED = "OPERATION ENABLED"
    QUICK_STOP_ACTIVE = "QUICK STOP ACTIVE"
    FAULT_REACTION_ACTIVE = "FAULT REACTION ACTIVE"
    FAULT = "FAULT"


class Command(Enum):
    """Device control commands (CiA 402-2, controlword bits 7, 3, 2, 1, 0)."""

    SHUTDOWN = "shutdown"
    SWITCH_ON = "switch on"
    SWITCH_ON_ENABLE = "switch on + enable operation"
    DISABLE_VOLTAGE = "disable voltage"
    QUICK_STOP = "quick stop"
    DISABLE_OPERATION = "disable operation"
    ENABLE_OPERATION = "enable operation"
    FAULT_RESET = "fault reset"


class Controlword(IntEnum):
    """Controlword bits (CiA 402-2)."""

    SWITCH_ON = 0x0001
    ENABLE_VOLTAGE = 0x0002
    QUICK_STOP = 0x0004
    ENABLE_OPERATION = 0x0008
    NEW_SET_POINT = 0x0010
    """Profile position mode: a new target on the 0 -> 1 edge."""
    CHANGE_SET_IMMEDIATELY = 0x0020
    ABS_REL = 0x0040
    """Profile position mode: 1 = the target is relative to the last one."""
    FAULT_RESET = 0x0080
    HALT = 0x0100


class Statusword(IntEnum):
    """Statusword bits (CiA 402-2)."""

    READY_TO_SWITCH_ON = 0x0001
    SWITCHED_ON = 0x0002
    OPERATION_ENABLED = 0x0004
    FAULT = 0x0008
    VOLTAGE_ENABLED = 0x0010
    QUICK_STOP = 0x0020
    """0 = quick stop active (the bit is low-active)."""
    SWITCH_ON_DISABLED = 0x0040
    WARNING = 0x0080
    MANUFACTURER_8 = 0x0100
    REMOTE = 0x0200
    TARGET_REACHED = 0x0400
    INTERNAL_LIMIT_ACTIVE = 0x0800
    SET_POINT_ACKNOWLEDGE = 0x1000
    """Profile position mode (bit 12)."""
    FOLLOWING_ERROR = 0x2000
    """Profile position mode (bit 13)."""
    MANUFACTURER_14 = 0x4000
    MANUFACTURER_15 = 0x8000


STATE_BITS: dict[State, int] = {
    State.NOT_READY_TO_SWITCH_ON: 0x0000,
    State.SWITCH_ON_DISABLED: 0x0040,
    State.READY_TO_SWITCH_ON: 0x0021,
    State.SWITCHED_ON: 0x0023,
    State.OPERATION_ENABLED: 0x0027,
    State.QUICK_STOP_ACTIVE: 0x0007,
    State.FAULT_REACTION_ACTIVE: 0x000F,
    State.FAULT: 0x0008,
}
"""Statusword bits 0-3, 5 and 6 of each state (CiA 402-2, statusword table)."""

VOLTAGE_STATES = frozenset({State.READY_TO_SWITCH_ON, State.SWITCHED_ON, State.OPERATION_ENABLED,
                            State.QUICK_STOP_ACTIVE})
"""States with the power stage (the hydraulic pressure, the drive's DC link) up: statusword bit 4."""


def decode(controlword: int, previous: int) -> Command | None:
    """The device control command of a controlword written after ``previous`` (None: no command).

    Bit 7's 0 -> 1 edge is FAULT RESET whatever bits 0-3 say; otherwise bits 0-3 (x = don't care):
    xx0x disable voltage, x01x quick stop, 0110 shutdown, 0111 switch on / disable operation, 1111 switch on +
    enable operation / enable operation. 1110 is shutdown too (bit 0 clear, bits 1-2 set)."""
    if controlword & Controlword.FAULT_RESET and not previous & Controlword.FAULT_RESET:
        return Command.FAULT_RESET
    low = controlword & 0x000F
    if not low & Controlword.ENABLE_VOLTAGE:
        return Command.DISABLE_VOLTAGE
    if not low & Controlword.QUICK_STOP:
        return Command.QUICK_STOP
    if not low & Controlword.SWITCH_ON:
        return Command.SHUTDOWN
    if low & Controlword.ENABLE_OPERATION:
        return Command.SWITCH_ON_ENABLE
    return Command.SWITCH_ON


def transition(state: State, command: Command | None) -> State:
    """The state after a command (CiA 402-2 transitions 2-12, 15); an unsupported command leaves it unchanged.

    SWITCH ON + ENABLE OPERATION from READY TO SWITCH ON makes transitions 3 and 4 in one step, as the profile
    allows; a quick stop from OPERATION ENABLED ends in SWITCH ON DISABLED (option code 2)."""
    if command is None:
        return state
    if state is State.FAULT:
        return State.SWITCH_ON_DISABLED if command is Command.FAULT_RESET else state
    if state in (State.NOT_READY_TO_SWITCH_ON, State.FAULT_REACTION_ACTIVE) or command is Command.FAULT_RESET:
        return state
    if command is Command.DISABLE_VOLTAGE:
        return State.SWITCH_ON_DISABLED
    if command is Command.QUICK_STOP:
        return State.SWITCH_ON_DISABLED
    if state is State.QUICK_STOP_ACTIVE:
        return State.OPERATION_ENABLED if command is Command.SWITCH_ON_ENABLE else state
    if command is Command.SHUTDOWN:
        return State.READY_TO_SWITCH_ON
    if command is Command.SWITCH_ON:
        return State.SWITCHED_ON if state in (State.READY_TO_SWITCH_ON, State.OPERATION_ENABLED) else state
    if state in (State.READY_TO_SWITCH_ON, State.SWITCHED_ON, State.OPERATION_ENABLED):
        return State.OPERATION_ENABLED
    return state


def statusword(state: State, extra: int = 0) -> int:
    """The statusword of a state: its state bits, voltage enabled (bit 4) where the power stage is up, remote (bit 9:
    the controlword is obeyed) and ``extra`` (the device's bits 7, 8, 10-15)."""
    word = STATE_BITS[state] | Statusword.REMOTE | (extra & 0xFD80)
    if state in VOLTAGE_STATES:
        word |= Statusword.VOLTAGE_ENABLED
    return word
