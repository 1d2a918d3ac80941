"""The argument forms of the methods the simulated CMM supports, checked from the specification (6.3).

Each reader takes a parsed ``wire.Command`` and returns what the method needs, or raises ``ArgumentError`` with the
error to answer: a wrong count or a malformed list 0502 Incorrect arguments, an argument of the wrong kind 0509
Bad argument (NIST's reference parser's numbering), an item used twice 0502 (6.1.3: an enumeration holds an item at
most once), and where the method's section names its own error, that one (OnPtMeasReport and OnMoveReportE: 0510
Bad property; IJK() outside a report: 0508 Bad context; SetCoordSystem: 0509; a form 1.4.3 defines but this server
does not implement: 0506 Argument not supported).
"""

from __future__ import annotations

from dataclasses import dataclass

from hilcal.protocols.ippdme import COORD_SYSTEMS, PARAMETER_PARTS, Code, Method
from sim_devices.cmm.tools import BLOCKS
from sim_devices.cmm.wire import Command, EventTag, Number, Property, String, Word

SUPPORTED = frozenset({
    Method.START_SESSION, Method.END_SESSION, Method.GET_DME_VERSION, Method.GET_MACHINE_CLASS, Method.IS_HOMED,
    Method.HOME, Method.ENABLE_USER, Method.DISABLE_USER, Method.IS_USER_ENABLED, Method.GET_ERR_STATUS_E,
    Method.GET_XTD_ERR_STATUS, Method.CLEAR_ALL_ERRORS, Method.ABORT_E, Method.GET_ERROR_INFO, Method.ENUM_TOOLS,
    Method.FIND_TOOL, Method.CHANGE_TOOL, Method.SET_TOOL, Method.GET_PROP, Method.GET_PROP_E, Method.SET_PROP,
    Method.ENUM_PROP, Method.ENUM_ALL_PROP, Method.ON_PT_MEAS_REPORT, Method.GET, Method.GO_TO, Method.PT_MEAS,
    Method.ON_MOVE_REPORT_E, Method.STOP_DAEMON, Method.STOP_ALL_DAEMONS, Method.SET_COORD_SYSTEM,
    Method.GET_COORD_SYSTEM,
})
"""Every other method of the specification is answered 0501 Unsupported command."""
NO_ARGUMENTS = frozenset({
    Method.START_SESSION, Method.END_SESSION, Method.GET_DME_VERSION, Method.GET_MACHINE_CLASS, Method.IS_HOMED,
    Method.HOME, Method.ENABLE_USER, Method.DISABLE_USER, Method.IS_USER_ENABLED, Method.GET_ERR_STATUS_E,
    Method.GET_XTD_ERR_STATUS, Method.CLEAR_ALL_ERRORS, Method.ABORT_E, Method.ENUM_TOOLS, Method.STOP_ALL_DAEMONS,
    Method.GET_COORD_SYSTEM,
})
TOOL_AXES = ("Tool.A", "Tool.B", "Tool.C")
"""The head's angles (6.3.8): the simulated probe head is fixed, they read 0."""
NOT_IMPLEMENTED_PROPERTIES = ("Id", "Alignment", "CollisionVolume", "AlignmentVolume", "ScanPar")
"""Tool properties of 1.4.3 this server does not implement (0506)."""


class ArgumentError(Exception):
    def __init__(self, code: Code, detail: str) -> None:
        super().__init__(detail)
        self.code = code
        self.detail = detail


def no_arguments(cmd: Command) -> None:
    if cmd.args:
        raise ArgumentError(Code.INCORRECT_ARGUMENTS, f"{cmd.method} takes no arguments")


def one_string(cmd: Command) -> str:
    (arg,) = _one(cmd)
    if not isinstance(arg, String):
        raise ArgumentError(Code.BAD_ARGUMENT, f"{cmd.method} needs a string")
    return arg.value


def error_number(cmd: Command) -> int:
    (arg,) = _one(cmd)
    if not isinstance(arg, Number) or arg.value != int(arg.value):
        raise ArgumentError(Code.BAD_ARGUMENT, "GetErrorInfo needs an integer")
    return int(arg.value)


def event_tag(cmd: Command) -> str:
    (arg,) = _one(cmd)
    if not isinstance(arg, EventTag):
        raise ArgumentError(Code.BAD_ARGUMENT, "StopDaemon needs an event tag")
    return arg.value


def coord_system(cmd: Command) -> str:
    """6.3.3.1: one of the coordinate systems, an enumeration value (0509 otherwise)."""
    (arg,) = _one(cmd)
    if not isinstance(arg, Word) or arg.value not in COORD_SYSTEMS:
        raise ArgumentError(Code.BAD_ARGUMENT, f"SetCoordSystem takes one of {', '.join(COORD_SYSTEMS)}")
    return arg.value


def _one(cmd: Command) -> tuple[object]:
    if len(cmd.args) != 1:
        raise ArgumentError(Code.INCORRECT_ARGUMENTS, f"{cmd.method} takes one argument")
    return (cmd.args[0],)


def _properties(cmd: Command, least: int = 1) -> list[Property]:
    if len(cmd.args) < least:
        raise ArgumentError(Code.INCORRECT_ARGUMENTS, f"{cmd.method} needs {least} argument(s) or more")
    out = []
    for arg in cmd.args:
        if not isinstance(arg, Property):
            raise ArgumentError(Code.INCORRECT_ARGUMENTS, f"{cmd.method}: {arg} is no property")
        out.append(arg)
    names = [p.name for p in out]
    for name in names:
        if names.count(name) > 1:
            raise ArgumentError(Code.INCORRECT_ARGUMENTS, f"{name} used twice (6.1.3)")
    return out


def query_items(cmd: Command) -> list[str]:
    """Get(..) (6.3.2.11): X(), Y(), Z(), Tool.A(), Tool.B(), Tool.C(), each without numbers."""
    items = []
    for prop in _properties(cmd):
        if prop.numbers:
            raise ArgumentError(Code.INCORRECT_ARGUMENTS, f"{prop.name}() takes no numbers in Get")
        if prop.name == "IJK":
            raise ArgumentError(Code.BAD_CONTEXT, "IJK() only in OnPtMeasReport or OnScanReport (6.3.3.8)")
        if prop.name in ("ER", "Q"):
            raise ArgumentError(Code.BAD_ARGUMENT, f"{prop.name}() only in an On...Report (6.3.2.24, 6.3.2.25)")
        if prop.name == "R":
            raise ArgumentError(Code.BAD_ARGUMENT, "R(): a CartCMM without rotary table (6.3.3.13)")
        if prop.name not in ("X", "Y", "Z", *TOOL_AXES):
            raise ArgumentError(Code.INCORRECT_ARGUMENTS, f"Get cannot query {prop.name}()")
        items.append(prop.name)
    return items


def report_items(cmd: Command) -> list[str]:
    """OnPtMeasReport(..) (6.3.2.6): Get's items and IJK(), ER(), Q(); not empty; 0510 for any other property."""
    items = []
    for prop in _properties(cmd):
        if prop.numbers:
            raise ArgumentError(Code.INCORRECT_ARGUMENTS, f"{prop.name}() takes no numbers in a report")
        if prop.name not in ("X", "Y", "Z", "IJK", "ER", "Q", *TOOL_AXES):
            raise ArgumentError(Code.BAD_PROPERTY, f"{prop.name}() cannot be reported by this CartCMM")
        items.append(prop.name)
    return items


@dataclass(frozen=True)
class MoveReport:
    time_s: float | None
    dis_mm: float | None
    items: tuple[str, ...]


def move_report(cmd: Command) -> MoveReport:
    """OnMoveReportE(Time(s), Dis(d), X(), ...) (6.3.2.7): Time at least 0.1 s, Dis above 0; 0510 otherwise."""
    time_s = dis_mm = None
    items: list[str] = []
    for prop in _properties(cmd, least=0):
        if prop.name in ("Time", "Dis"):
            if len(prop.numbers) != 1:
                raise ArgumentError(Code.BAD_ARGUMENT, f"{prop.name} needs one number")
            value = prop.numbers[0]
            if prop.name == "Time" and value < 0.1:
                raise ArgumentError(Code.BAD_PROPERTY, "Time must not be less than 0.1 (6.3.2.7)")
            if prop.name == "Dis" and value <= 0:
                raise ArgumentError(Code.BAD_PROPERTY, "Dis must be above 0")
            time_s, dis_mm = (value, dis_mm) if prop.name == "Time" else (time_s, value)
        elif prop.numbers:
            raise ArgumentError(Code.INCORRECT_ARGUMENTS, f"{prop.name}() takes no numbers in a report")
        elif prop.name not in ("X", "Y", "Z", *TOOL_AXES):
            raise ArgumentError(Code.BAD_PROPERTY, f"{prop.name} cannot be reported while moving")
        else:
            items.append(prop.name)
    return MoveReport(time_s, dis_mm, tuple(items))


def _axes(props: list[Property], code_for_count: Code) -> dict[str, float]:
    axes: dict[str, float] = {}
    for prop in props:
        if prop.name in ("X", "Y", "Z"):
            if len(prop.numbers) != 1:
                raise ArgumentError(code_for_count, f"{prop.name} needs one number")
            axes[prop.name] = prop.numbers[0]
    return axes


def goto_target(cmd: Command) -> dict[str, float]:
    """GoTo(X(x), Y(y), Z(z)) (6.3.2.12): one or more axes; the head's angles and R() are not supported here."""
    props = _properties(cmd)
    for prop in props:
        if prop.name in (*TOOL_AXES, "R") and len(prop.numbers) != 1:
            raise ArgumentError(Code.INCORRECT_ARGUMENTS, f"{prop.name} needs one number")
        if prop.name in (*TOOL_AXES, "R"):
            raise ArgumentError(Code.ARGUMENT_NOT_SUPPORTED, f"{prop.name}(..): a fixed probe head, no rotary table")
        if prop.name == "IJK":
            raise ArgumentError(Code.BAD_CONTEXT, "IJK(..) is no GoTo argument")
        if prop.name not in ("X", "Y", "Z"):
            raise ArgumentError(Code.INCORRECT_ARGUMENTS, f"{prop.name} is no GoTo argument")
    return _axes(props, Code.INCORRECT_ARGUMENTS)


def ptmeas_target(cmd: Command) -> tuple[dict[str, float], tuple[float, float, float] | None]:
    """PtMeas(X(x), Y(y), Z(z), IJK(i,j,k)) (6.3.2.13): one to four arguments, IJK never alone."""
    props = _properties(cmd)
    ijk = None
    for prop in props:
        if prop.name == "IJK":
            if len(prop.numbers) != 3:
                raise ArgumentError(Code.INCORRECT_ARGUMENTS, "IJK needs three numbers")
            ijk = (prop.numbers[0], prop.numbers[1], prop.numbers[2])
        elif prop.name not in ("X", "Y", "Z"):
            raise ArgumentError(Code.INCORRECT_ARGUMENTS, f"{prop.name} is no PtMeas argument")
    axes = _axes(props, Code.BAD_ARGUMENT)
    if not axes:
        raise ArgumentError(Code.INCORRECT_ARGUMENTS, "IJK(..) without a linear axis is not allowed (6.3.2.13)")
    return axes, ijk


@dataclass(frozen=True)
class PropertyRef:
    """A tool property named in GetProp, SetProp or EnumProp: ``owner.path`` as the client wrote it."""

    owner: str
    """``Tool`` or ``FoundTool``."""
    path: tuple[str, ...]
    """``("PtMeasPar", "Speed")``, ``("PtMeasPar", "Speed", "Max")``, ``("Name",)``, ``("AvrRadius",)`` or ``()``."""
    value: float | None = None

    @property
    def text(self) -> str:
        return ".".join((self.owner, *self.path))


def _property_ref(prop: Property, enumerating: bool = False) -> PropertyRef:
    owner, *path = prop.name.split(".")
    if owner not in ("Tool", "FoundTool"):
        raise ArgumentError(Code.BAD_ARGUMENT, f"{prop.name}: a property of Tool() or FoundTool()")
    ref = PropertyRef(owner, tuple(path))
    if not path:
        if not enumerating:
            raise ArgumentError(Code.BAD_ARGUMENT, f"{prop.name}() is no value")
        return ref
    if path[0] in BLOCKS:
        if len(path) == 1 and enumerating:
            return ref
        if len(path) == 1 or path[1] not in BLOCKS[path[0]]:
            raise ArgumentError(Code.BAD_ARGUMENT, f"{prop.name}: {path[0]} has {', '.join(BLOCKS[path[0]])}")
        if len(path) > 3 or (len(path) == 3 and path[2] not in PARAMETER_PARTS):
            raise ArgumentError(Code.BAD_ARGUMENT, f"{prop.name}: a parameter has {', '.join(PARAMETER_PARTS)}")
        return ref
    if path in (["Name"], ["AvrRadius"]) and not enumerating and not (path[0] == "AvrRadius" and owner != "Tool"):
        return ref
    if owner == "FoundTool" and path[0] in ("Alignment", "CollisionVolume"):
        raise ArgumentError(Code.INCORRECT_ARGUMENTS, f"{prop.name}: a property of the active tool only (6.3.11)")
    if path[0] in NOT_IMPLEMENTED_PROPERTIES:
        raise ArgumentError(Code.ARGUMENT_NOT_SUPPORTED, f"{prop.name}() is not implemented by this server")
    raise ArgumentError(Code.BAD_ARGUMENT, f"{prop.name} is no tool property")


def get_properties(cmd: Command) -> list[PropertyRef]:
    """GetProp(..), GetPropE(..) (6.3.1.9): properties without numbers."""
    refs = []
    for prop in _properties(cmd):
        if prop.numbers:
            raise ArgumentError(Code.BAD_ARGUMENT, f"{prop.name}(): no numbers when getting")
        refs.append(_property_ref(prop))
    return refs


def set_properties(cmd: Command) -> list[PropertyRef]:
    """SetProp(..) (6.3.1.11): parameters' Act values, one number each (Min, Max and Def cannot be set)."""
    refs = []
    for prop in _properties(cmd):
        ref = _property_ref(prop)
        if not ref.path or ref.path[0] not in BLOCKS:
            raise ArgumentError(Code.BAD_ARGUMENT, f"{prop.name} cannot be set")
        if len(ref.path) == 3 and ref.path[2] != "Act":
            raise ArgumentError(Code.BAD_ARGUMENT, "only Act can be set (6.3.6, 6.3.7)")
        if len(prop.numbers) != 1:
            raise ArgumentError(Code.BAD_ARGUMENT, f"{prop.name} needs one number")
        refs.append(PropertyRef(ref.owner, ref.path, prop.numbers[0]))
    return refs


def enum_property(cmd: Command) -> PropertyRef:
    """EnumProp(..), EnumAllProp(..) (6.3.1.12, 6.3.1.13): one property to list the children of."""
    (arg,) = _one(cmd)
    if not isinstance(arg, Property):
        raise ArgumentError(Code.INCORRECT_ARGUMENTS, f"{cmd.method} needs a property such as Tool.PtMeasPar()")
    if arg.numbers:
        raise ArgumentError(Code.BAD_ARGUMENT, f"{arg.name}(): no numbers when enumerating")
    return _property_ref(arg, enumerating=True)  # a parameter's part is a number: no children (as NIST's server)
