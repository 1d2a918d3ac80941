"""I++ DME 1.4.3, the CMM interface: declarative tables only (names, codes, texts, the grammar's atoms).

The driver (``drivers/cmm/``) and the simulated CMM (``sim_devices/cmm/``) both read these tables, but each side has
its own parser and formatter, so the simulator cannot agree with the driver merely by sharing its code. Section
numbers are those of the specification (``I++ DME Specification 1.4.3``); ``docs/protocols.md`` says which commands
the driver uses, ``docs/cmm_simulator.md`` what the simulator supports and where 1.4.3 and later versions differ.

Line grammar (6.1.4.2, abridged; 6.2: ASCII 32..126, CR LF terminated, at most 65536 characters)::

    Command        :== (Tag | ETag) s Method
    AckResponse    :== (Tag | ETag) s "&"
    DoneResponse   :== (Tag | ETag) s "%"
    DataResponse   :== (Tag | ETag) s "#" s DataData
    ErrorResponse  :== (Tag | ETag) s "!" s "Error" "(" F1 "," F2 "," F3 "," Text ")"
    Tag            :== 5 digits, 00001..99999       ETag :== "E" 4 digits, E0001..E9999
    ETag0          :== "E0000"                       (unsolicited server events only, 6.2.1)

A transaction (6.2.3) is ``&`` first, then any ``#`` and ``!`` lines, then ``%`` last; ``!`` never ends it.
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import IntEnum, StrEnum

SPEC_VERSION = "1.4.3"
ENCODING = "ascii"
TERMINATOR = b"\r\n"
"""6.1.1: CR and LF, always as a pair, only at the end of a line."""
MAX_LINE_CHARS = 65536
"""6.2: a line should not exceed 65536 characters (terminator excluded)."""
PRINTABLE_MIN, PRINTABLE_MAX = 0x20, 0x7E
"""6.1.1: the only characters a line may hold besides its terminator."""
DEFAULT_TCP_PORT = 1294
"""6.1: the application port."""

# ------------------------------------------------------------------ tags (6.2.1)

TAG_MIN, TAG_MAX = 1, 99999
EVENT_TAG_MIN, EVENT_TAG_MAX = 1, 9999
SERVER_EVENT_TAG = "E0000"
"""ETag0: unsolicited server events and errors (an emergency stop, an illegal tag) carry it."""
TAG_PATTERN = r"(?!00000)[0-9]{5}"
EVENT_TAG_PATTERN = r"E(?!0000)[0-9]{4}"

# ------------------------------------------------------------------ grammar atoms (6.1.4.2)

BASIC_NAME_PATTERN = r"[A-Za-z][A-Za-z0-9]*"
NAME_PATTERN = rf"{BASIC_NAME_PATTERN}(?:\.{BASIC_NAME_PATTERN})*"
NUMBER_PATTERN = r"[+-]?(?:[0-9]+\.?[0-9]*|\.[0-9]+)(?:[Ee][+-]?[0-9]{1,3})?"
MAX_NUMBER_DIGITS = 16
"""Number: "the total number of digits shall not exceed 16" (6.1.4.2), counted before the exponent as NIST's parsers
count them (NIST's DCXpart.prg sends 16 digits and a three-digit exponent)."""
STRING_PATTERN = r'"[ !#-~]+"'
"""String :== q Char {Char} q: at least one character, none of them a double quote."""
OPTIONAL_SPACE = " "
"""Optional spaces may stand before or after a comma, before or after "(", and before ")": nowhere else."""


class Marker(StrEnum):
    """The seventh character of a response line (6.2.2.2)."""

    ACK = "&"
    DONE = "%"
    DATA = "#"
    ERROR = "!"


# ------------------------------------------------------------------ errors (8)


class Severity(IntEnum):
    """F1 of an error (8.1). Severity 2 and above abort pending transactions and need ClearAllErrors() (6.2.5)."""

    INFO = 0
    WARNING = 1
    ERROR = 2
    """The client should be able to repair the error."""
    USER = 3
    """User interaction is necessary."""
    FATAL = 9


NEEDS_CLEAR = Severity.ERROR
"""6.2.5, 8.1: errors of this severity or higher need ClearAllErrors() before other commands are processed."""


@dataclass(frozen=True)
class ErrorSpec:
    """One row of the table of 8.2: the default severity and the exact text."""

    code: int
    severity: Severity
    text: str


_TABLE = (
    (0, 0, "Buffer full"),
    (1, 2, "Illegal tag"),
    (2, 2, "No space at pos. 6"),
    (3, 2, "Reserved"),
    (4, 2, "Reserved"),
    (5, 2, "Reserved"),
    (6, 2, "Transaction aborted (Use ClearAllErrors To Continue)"),
    (7, 3, "Illegal character"),
    (8, 3, "Protocol error"),
    (500, 3, "Emergency stop"),
    (501, 3, "Unsupported command"),
    (502, 3, "Incorrect arguments"),
    (503, 9, "Controller communications failure"),
    (504, 1, "Argument out of range"),
    (505, 3, "Argument not recognized"),
    (506, 3, "Argument not supported"),
    (507, 3, "Illegal command"),
    (508, 3, "Bad context"),
    (509, 3, "Bad argument"),
    (510, 3, "Bad property"),
    (511, 3, "Error processing method"),
    (512, 1, "No daemons are active"),
    (513, 2, "Daemon does not exist"),
    (514, 2, "Use ClearAllErrors to continue"),
    (515, 2, "Daemon already exists"),
    (1000, 3, "Machine in error state"),
    (1001, 2, "Illegal touch"),
    (1002, 9, "Axis does not exist"),
    (1003, 2, "No touch"),
    (1004, 9, "Number of angles not supported on current device"),
    (1005, 3, "Error during home"),
    (1006, 2, "Surface not found"),
    (1007, 3, "Theta out of range"),
    (1008, 3, "Target position out of machine volume"),
    (1009, 3, "Air pressure out of range"),
    (1010, 2, "Vector has no norm"),
    (1011, 2, "Unable to move"),
    (1012, 2, "Bad lock combinations"),
    (1500, 3, "Failed to re-seat head"),
    (1501, 3, "Probe not armed"),
    (1502, 3, "Tool not found"),
    (1503, 3, "Tool not defined"),
    (2000, 3, "Tool not calibrated"),
    (2001, 2, "Head error excessive force"),
    (2002, 3, "Type of probe does not allow this operation"),
    (2500, 3, "Machine limit encountered [Move Out Of Limits]"),
    (2501, 3, "Axis not active"),
    (2502, 3, "Axis position error"),
    (2503, 9, "Scale read head failure"),
    (2504, 3, "Collision"),
    (2505, 2, "Specified angle out of range"),
    (2506, 2, "Part not aligned"),
)

ERRORS: dict[int, ErrorSpec] = {code: ErrorSpec(code, Severity(sev), text) for code, sev, text in _TABLE}
"""8.2, the predefined errors by number (F2)."""
SERVER_DEFINED_CODES = range(8000, 9000)
"""8.1: error numbers a server may define itself (texts its own)."""
CLIENT_DEFINED_CODES = range(9000, 10000)


class Code(IntEnum):
    """The error numbers hilcal's driver and simulator name in their code."""

    BUFFER_FULL = 0
    ILLEGAL_TAG = 1
    NO_SPACE_AT_POS_6 = 2
    TRANSACTION_ABORTED = 6
    ILLEGAL_CHARACTER = 7
    PROTOCOL_ERROR = 8
    EMERGENCY_STOP = 500
    UNSUPPORTED_COMMAND = 501
    INCORRECT_ARGUMENTS = 502
    ARGUMENT_OUT_OF_RANGE = 504
    ARGUMENT_NOT_RECOGNIZED = 505
    ARGUMENT_NOT_SUPPORTED = 506
    ILLEGAL_COMMAND = 507
    BAD_CONTEXT = 508
    BAD_ARGUMENT = 509
    BAD_PROPERTY = 510
    ERROR_PROCESSING_METHOD = 511
    NO_DAEMONS_ARE_ACTIVE = 512
    DAEMON_DOES_NOT_EXIST = 513
    USE_CLEAR_ALL_ERRORS = 514
    DAEMON_ALREADY_EXISTS = 515
    MACHINE_IN_ERROR_STATE = 1000
    ILLEGAL_TOUCH = 1001
    NO_TOUCH = 1003
    ERROR_DURING_HOME = 1005
    SURFACE_NOT_FOUND = 1006
    TARGET_OUT_OF_VOLUME = 1008
    VECTOR_HAS_NO_NORM = 1010
    UNABLE_TO_MOVE = 1011
    TOOL_NOT_FOUND = 1502
    TOOL_NOT_DEFINED = 1503
    MACHINE_LIMIT = 2500
    COLLISION = 2504


PROBE_MISS_CODES = frozenset({Code.NO_TOUCH, Code.SURFACE_NOT_FOUND})
"""PtMeas touched nothing within its search (6.3.2.13: 1006; 1003 where a server says so)."""

# ------------------------------------------------------------------ methods (6.3, 11, 12, 13)


class Method(StrEnum):
    """The methods of the specification (case-sensitive). Names ending in E are for the fast queue (6.2.1)."""

    START_SESSION = "StartSession"
    END_SESSION = "EndSession"
    STOP_DAEMON = "StopDaemon"
    STOP_ALL_DAEMONS = "StopAllDaemons"
    ABORT_E = "AbortE"
    GET_ERROR_INFO = "GetErrorInfo"
    CLEAR_ALL_ERRORS = "ClearAllErrors"
    GET_PROP = "GetProp"
    GET_PROP_E = "GetPropE"
    SET_PROP = "SetProp"
    ENUM_PROP = "EnumProp"
    ENUM_ALL_PROP = "EnumAllProp"
    GET_DME_VERSION = "GetDMEVersion"
    HOME = "Home"
    IS_HOMED = "IsHomed"
    ENABLE_USER = "EnableUser"
    DISABLE_USER = "DisableUser"
    IS_USER_ENABLED = "IsUserEnabled"
    ON_PT_MEAS_REPORT = "OnPtMeasReport"
    ON_MOVE_REPORT_E = "OnMoveReportE"
    GET_MACHINE_CLASS = "GetMachineClass"
    GET_ERR_STATUS_E = "GetErrStatusE"
    GET_XTD_ERR_STATUS = "GetXtdErrStatus"
    GET = "Get"
    GO_TO = "GoTo"
    PT_MEAS = "PtMeas"
    FIND_TOOL = "FindTool"
    CHANGE_TOOL = "ChangeTool"
    SET_TOOL = "SetTool"
    ALIGN_TOOL = "AlignTool"
    ENUM_TOOLS = "EnumTools"
    GET_CHANGE_TOOL_ACTION = "GetChangeToolAction"
    SET_COORD_SYSTEM = "SetCoordSystem"
    GET_COORD_SYSTEM = "GetCoordSystem"
    GET_CSY_TRANSFORMATION = "GetCsyTransformation"
    SET_CSY_TRANSFORMATION = "SetCsyTransformation"
    RE_QUALIFY = "ReQualify"
    ON_SCAN_REPORT = "OnScanReport"
    SCAN_ON_CIRCLE_HINT = "ScanOnCircleHint"
    SCAN_ON_CIRCLE = "ScanOnCircle"
    SCAN_ON_LINE_HINT = "ScanOnLineHint"
    SCAN_ON_LINE = "ScanOnLine"
    SCAN_ON_CURVE_HINT = "ScanOnCurveHint"
    SCAN_ON_CURVE_DENSITY = "ScanOnCurveDensity"
    SCAN_ON_CURVE = "ScanOnCurve"
    SCAN_UNKNOWN_HINT = "ScanUnknownHint"
    SCAN_UNKNOWN_DENSITY = "ScanUnknownDensity"
    SCAN_IN_PLANE_END_IS_SPHERE = "ScanInPlaneEndIsSphere"
    SCAN_IN_PLANE_END_IS_PLANE = "ScanInPlaneEndIsPlane"
    SCAN_IN_PLANE_END_IS_CYL = "ScanInPlaneEndIsCyl"
    SCAN_IN_CYL_END_IS_SPHERE = "ScanInCylEndIsSphere"
    SCAN_IN_CYL_END_IS_PLANE = "ScanInCylEndIsPlane"
    ALIGN_PART = "AlignPart"
    CENTER_PART = "CenterPart"
    TILT_PART = "TiltPart"
    TILT_CENTER_PART = "TiltCenterPart"
    LOCK_AXIS = "LockAxis"
    LOCK_POSITION = "LockPosition"
    """13.5, new in 1.4.3."""


EVENT_METHODS = frozenset(m for m in Method if m.endswith("E"))
"""Methods sent with an event tag on the fast queue (6.2.1: only these may carry one)."""
SESSIONLESS_METHODS = frozenset({Method.START_SESSION, Method.END_SESSION})
"""6.3.1: without a session the server accepts only these."""
WHILE_IN_ERROR_METHODS = frozenset({Method.GET_ERR_STATUS_E, Method.GET_XTD_ERR_STATUS, Method.CLEAR_ALL_ERRORS})
"""6.2.5: in an error state of severity 2 or more the client may send only these."""
MOTION_METHODS = frozenset({Method.HOME, Method.GO_TO, Method.PT_MEAS, Method.CHANGE_TOOL, Method.ALIGN_TOOL,
                            Method.ALIGN_PART, Method.CENTER_PART, Method.TILT_PART, Method.TILT_CENTER_PART})
"""Methods that move the machine (6.3.2.4 lists those that imply DisableUser(); scans move it too)."""

# ------------------------------------------------------------------ reports, properties, tools, classes

DEFAULT_PT_MEAS_REPORT = ("X", "Y", "Z")
"""6.3.1.1: StartSession() sets OnPtMeasReport(X(), Y(), Z())."""
PT_MEAS_REPORT_ITEMS = frozenset({"X", "Y", "Z", "IJK", "ER", "Q", "R", "Tool.A", "Tool.B", "Tool.C"})
"""6.3.2.6: what OnPtMeasReport may ask for (Get's arguments and IJK(), ER(), Q())."""

PT_MEAS_PAR = "Tool.PtMeasPar"
PT_MEAS_PARAMETERS = ("Speed", "Accel", "Approach", "Search", "Retract")
"""6.3.7: the PtMeasPar block, each a parameter with Min, Max, Act and Def."""
GO_TO_PAR = "Tool.GoToPar"
GO_TO_PARAMETERS = ("Speed", "Accel")
"""6.3.6: the GoToPar block."""
PARAMETER_PARTS = ("Min", "Max", "Act", "Def")
"""A parameter's parts; a parameter named without one means its Act (6.3.6, 6.3.7); only Act can be set."""
AVR_RADIUS = "Tool.AvrRadius"
"""6.3.13: GetProp(Tool.AvrRadius()) answers the active tool's average tip radius (mm; 0 where it has none)."""
TOOL_NAME = "Tool.Name"
"""6.3.10: GetProp(Tool.Name()) answers the active tool's name."""

RESERVED_TOOLS = ("BaseTool", "RefTool", "NoTool", "UnDefTool")
"""6.3.2.14: predefined tool names. EnumTools lists RefTool and NoTool, never BaseTool or UnDefTool."""
NO_TOOL = "NoTool"
UNDEF_TOOL = "UnDefTool"

MACHINE_CLASSES = ("CartCMM", "CartCMMWithRotaryTable")
"""6.3.2.8: GetMachineClass() answers one of these (an enumeration, not a string, since 1.4.3)."""
COORD_SYSTEMS = ("MachineCsy", "MoveableMachineCsy", "MultipleArmCsy", "PartCsy")
"""6.3.3.1: SetCoordSystem()'s arguments (enums, unquoted)."""
CSY_TRANSFORMATIONS = ("PartCsy", "JogDisplayCsy", "JogMoveCsy", "SensorCsy", "MoveableMachineCsy", "MultipleArmCsy")
"""6.3.3.3, 6.3.3.4: the transformations GetCsyTransformation() and SetCsyTransformation() name."""
CHANGE_TOOL_ACTIONS = ("Switch", "Rotate", "MoveAuto", "MoveMan")
"""6.3.2.26: GetChangeToolAction()'s first datum."""
