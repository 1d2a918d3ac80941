"""Controller state machine, command, refusal-reason and fault codes shared by the driver and the simulator.

The state machine (both sides enforce it; see docs/protocols.md):

    DISABLED --ENABLE--> ENABLED --setpoint--> MOVING --all legs settled--> IN_POSITION --setpoint--> MOVING
    ENABLED/MOVING/IN_POSITION --DISABLE--> DISABLED;  --STOP--> ENABLED (holds the current lengths)
    any state --fault--> FAULT --FAULT_RESET--> DISABLED
    any state --e-stop--> ESTOP (latched) --FAULT_RESET, e-stop input released--> DISABLED

The numeric values are wire values (CAN signals and Modbus registers): never renumber them.
"""

from __future__ import annotations

from collections.abc import Mapping
from enum import IntEnum


class ControllerState(IntEnum):
    """Servo controller state (4-bit CAN signal ``State``, Modbus register CONTROLLER_STATE)."""

    DISABLED = 0
    ENABLED = 1
    MOVING = 2
    IN_POSITION = 3
    FAULT = 4
    ESTOP = 5


class Command(IntEnum):
    """Command codes (CAN signal ``CommandCode``); SETPOINT only appears in acknowledgements."""

    ENABLE = 1
    DISABLE = 2
    STOP = 3
    FAULT_RESET = 4
    SETPOINT = 16


class RefusalReason(IntEnum):
    """Result of a command or setpoint (CAN signal ``Reason`` of CommandAck); 0 means accepted."""

    ACCEPTED = 0
    WRONG_STATE = 1
    FAULT_ACTIVE = 2
    ESTOP_ACTIVE = 3
    ESTOP_NOT_RELEASED = 4
    SETPOINT_OUT_OF_LIMITS = 5
    SETPOINT_INCOMPLETE = 6
    UNKNOWN_COMMAND = 7


class FaultCode(IntEnum):
    """Why the controller is in FAULT or ESTOP (CAN signal ``FaultCode``, Modbus register FAULT_CODE)."""

    NONE = 0
    FOLLOWING_ERROR = 1
    HYDRAULIC_PRESSURE = 2
    LEG_LIMIT = 3
    DRIVE = 4
    ENCODER = 5
    INTERNAL = 6
    ESTOP_INPUT = 16
    ESTOP_REQUEST = 17


MOTION_STATES: frozenset[ControllerState] = frozenset(
    {ControllerState.ENABLED, ControllerState.MOVING, ControllerState.IN_POSITION}
)

ALLOWED_STATES: Mapping[Command, frozenset[ControllerState]] = {
    Command.ENABLE: frozenset({ControllerState.DISABLED}),
    Command.DISABLE: MOTION_STATES,
    Command.STOP: MOTION_STATES,
    Command.FAULT_RESET: frozenset({ControllerState.FAULT, ControllerState.ESTOP}),
    Command.SETPOINT: MOTION_STATES,
}
"""States in which each command is accepted (FAULT_RESET in ESTOP also needs the e-stop input released)."""

TARGET_STATE: Mapping[Command, ControllerState] = {
    Command.ENABLE: ControllerState.ENABLED,
    Command.DISABLE: ControllerState.DISABLED,
    Command.STOP: ControllerState.ENABLED,
    Command.FAULT_RESET: ControllerState.DISABLED,
    Command.SETPOINT: ControllerState.MOVING,
}
"""State right after an accepted command."""


def refusal_reason(state: ControllerState, command: Command) -> RefusalReason:
    """Reason a command is refused in a state by the transition table (ACCEPTED when the table allows it)."""
    if state in ALLOWED_STATES[command]:
        return RefusalReason.ACCEPTED
    if state is ControllerState.FAULT:
        return RefusalReason.FAULT_ACTIVE
    if state is ControllerState.ESTOP:
        return RefusalReason.ESTOP_ACTIVE
    return RefusalReason.WRONG_STATE
