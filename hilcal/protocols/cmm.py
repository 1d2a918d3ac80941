"""The CMM wire protocol, modelled on I++ DME: declarative constants only (names, codes, grammar).

Both the driver (``drivers.cmm.serial``) and the simulator (``sim_devices.cmm.server``) read these
tables, but each side has its own parser and formatter, so the simulator cannot agree with the driver
merely by sharing its code. The protocol is described in ``docs/protocols.md (CMM section)``.

Line grammar (ASCII, one command or response per line)::

    line      = tag SP body CRLF
    tag       = 5 DIGIT                       ; 00001..99999, "00000" = server message (tag unreadable)
    command   = name "(" [ arg *( "," arg ) ] ")"
    arg       = number | string | name "(" [ arg *( "," arg ) ] ")"
    name      = ALPHA *( ALNUM ) *( "." ALPHA *( ALNUM ) )
    response  = "&"                           ; acknowledged: the command is accepted
              | "#" SP item *( "," item )     ; data
              | "%"                           ; done: the transaction is complete
              | "!" SP "Error(" severity "," code "," string "," string ")"

Spaces are allowed after commas. A transaction ends with exactly one terminal line: ``%`` or ``!``.
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import IntEnum, StrEnum

ENCODING = "ascii"
TERMINATOR = b"\r\n"
TAG_DIGITS = 5
TAG_MIN = 1
TAG_MAX = 99999
SERVER_TAG = "00000"
"""Tag of server responses to a line whose own tag could not be read."""
MAX_LINE_BYTES = 512
"""Longest line (terminator excluded) either side accepts; longer input is a protocol error."""

TAG_PATTERN = r"[0-9]{5}"
NAME_PATTERN = r"[A-Za-z][A-Za-z0-9]*(?:\.[A-Za-z][A-Za-z0-9]*)*"
NUMBER_PATTERN = r"[-+]?(?:[0-9]+(?:\.[0-9]*)?|\.[0-9]+)(?:[eE][-+]?[0-9]+)?"
STRING_PATTERN = r'"[^"\r\n]*"'
"""Strings are double-quoted and contain no double quote, CR or LF."""
PRINTABLE_MIN = 0x20
PRINTABLE_MAX = 0x7E

COORDINATE_DECIMALS = 6
"""Decimals the simulator prints for coordinates (1 nm); the driver accepts any number."""
MACHINE_VOLUME_LIMIT_MM = 100_000.0
"""|coordinate| beyond this is outside any machine volume (error 1008)."""
DEFAULT_SEARCH_DISTANCE_MM = 10.0
MAX_SEARCH_DISTANCE_MM = 100.0


class Marker(StrEnum):
    """First character of a response body."""

    ACK = "&"
    DATA = "#"
    DONE = "%"
    ERROR = "!"


class Command(StrEnum):
    """Command names (case-sensitive)."""

    START_SESSION = "StartSession"
    END_SESSION = "EndSession"
    HOME = "Home"
    CLEAR_ALL_ERRORS = "ClearAllErrors"
    GET_ERROR_INFO = "GetErrorInfo"
    GO_TO = "GoTo"
    PT_MEAS = "PtMeas"
    SET_PROP = "SetProp"


SEARCH_PROPERTY = "Tool.PtMeasPar.Search"
"""``SetProp(Tool.PtMeasPar.Search(d))``: search distance d (mm) of PtMeas on either side of the target."""
MOTION_COMMANDS = frozenset({Command.HOME, Command.GO_TO, Command.PT_MEAS})
"""Commands refused while the machine is in the error state."""
SESSION_FREE_COMMANDS = frozenset({Command.START_SESSION, Command.GET_ERROR_INFO})
"""Commands accepted outside a session."""


class Severity(IntEnum):
    """Error severity, as in I++ DME."""

    INFO = 0
    WARNING = 1
    ABORTED = 2
    """The command was aborted; after a latching error the machine needs ClearAllErrors."""
    REJECTED = 3
    """The command was refused; the machine state is unchanged."""
    FATAL = 9


class ErrorCode(IntEnum):
    """Error codes (numbering and texts follow I++ DME)."""

    BUFFER_FULL = 0
    ILLEGAL_TAG = 1
    NO_SPACE_AT_POS_6 = 2
    TRANSACTION_ABORTED = 6
    ILLEGAL_CHARACTER = 7
    PROTOCOL_ERROR = 8
    UNSUPPORTED_COMMAND = 501
    INCORRECT_ARGUMENTS = 502
    ARGUMENT_OUT_OF_RANGE = 504
    BAD_CONTEXT = 508
    BAD_PROPERTY = 510
    MACHINE_IN_ERROR_STATE = 1000
    ILLEGAL_TOUCH = 1001
    NO_TOUCH = 1003
    SURFACE_NOT_FOUND = 1006
    OUT_OF_MACHINE_VOLUME = 1008
    VECTOR_HAS_NO_NORM = 1010
    COLLISION = 2504


@dataclass(frozen=True)
class ErrorSpec:
    """Severity and standard text of one error code."""

    severity: Severity
    text: str


ERRORS: dict[ErrorCode, ErrorSpec] = {
    ErrorCode.BUFFER_FULL: ErrorSpec(Severity.INFO, "Buffer full"),
    ErrorCode.ILLEGAL_TAG: ErrorSpec(Severity.ABORTED, "Illegal tag"),
    ErrorCode.NO_SPACE_AT_POS_6: ErrorSpec(Severity.ABORTED, "No space at pos. 6"),
    ErrorCode.TRANSACTION_ABORTED: ErrorSpec(Severity.ABORTED, "Transaction aborted (Use ClearAllErrors to Continue)"),
    ErrorCode.ILLEGAL_CHARACTER: ErrorSpec(Severity.REJECTED, "Illegal character"),
    ErrorCode.PROTOCOL_ERROR: ErrorSpec(Severity.REJECTED, "Protocol error"),
    ErrorCode.UNSUPPORTED_COMMAND: ErrorSpec(Severity.REJECTED, "Unsupported command"),
    ErrorCode.INCORRECT_ARGUMENTS: ErrorSpec(Severity.REJECTED, "Incorrect arguments"),
    ErrorCode.ARGUMENT_OUT_OF_RANGE: ErrorSpec(Severity.WARNING, "Argument out of range"),
    ErrorCode.BAD_CONTEXT: ErrorSpec(Severity.REJECTED, "Bad context"),
    ErrorCode.BAD_PROPERTY: ErrorSpec(Severity.REJECTED, "Bad property"),
    ErrorCode.MACHINE_IN_ERROR_STATE: ErrorSpec(Severity.REJECTED, "Machine in error state"),
    ErrorCode.ILLEGAL_TOUCH: ErrorSpec(Severity.ABORTED, "Illegal touch"),
    ErrorCode.NO_TOUCH: ErrorSpec(Severity.ABORTED, "No touch"),
    ErrorCode.SURFACE_NOT_FOUND: ErrorSpec(Severity.ABORTED, "Surface not found"),
    ErrorCode.OUT_OF_MACHINE_VOLUME: ErrorSpec(Severity.REJECTED, "Target position out of machine volume"),
    ErrorCode.VECTOR_HAS_NO_NORM: ErrorSpec(Severity.ABORTED, "Vector has no norm"),
    ErrorCode.COLLISION: ErrorSpec(Severity.ABORTED, "Collision"),
}

LATCHING_ERRORS = frozenset(
    {ErrorCode.ILLEGAL_TOUCH, ErrorCode.NO_TOUCH, ErrorCode.SURFACE_NOT_FOUND, ErrorCode.COLLISION}
)
"""Errors that put the machine in the error state: motion commands then answer TRANSACTION_ABORTED
until ClearAllErrors (or a new StartSession)."""
PROBE_MISS_ERRORS = frozenset({ErrorCode.NO_TOUCH, ErrorCode.SURFACE_NOT_FOUND})
"""Errors of PtMeas that mean no surface was touched within the search distance."""
