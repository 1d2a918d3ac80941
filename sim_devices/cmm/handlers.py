"""What each supported method does and answers (6.3), given a session's state and the shared machine.

A handler fills a ``Reply`` with the transaction's ``#`` and ``!`` lines (``&`` and ``%`` are the session's); its
checks follow the order of NIST's command checker where the specification is silent (not homed 0507, the active tool
UnDefTool 1503, NoTool asked to measure 0507). Motions are the session's (``Motion`` plans from the machine, run by the
session so that AbortE and an emergency stop can halt them); ``motion_for`` returns the plan or answers the refusal.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from hilcal.protocols.ippdme import (
    DEFAULT_PT_MEAS_REPORT,
    ERRORS,
    NEEDS_CLEAR,
    NO_TOOL,
    PARAMETER_PARTS,
    SPEC_VERSION,
    UNDEF_TOOL,
    Code,
    Marker,
    Method,
)
from sim_devices.cmm import methods
from sim_devices.cmm.faults import FaultPlan
from sim_devices.cmm.machine import CmmMachine, Motion
from sim_devices.cmm.methods import MoveReport, PropertyRef
from sim_devices.cmm.responses import error_line, line, number, severity, string
from sim_devices.cmm.tools import BASE_TOOL, BLOCKS, Tool
from sim_devices.cmm.wire import Command


@dataclass
class Daemon:
    """OnMoveReportE's daemon (6.3.2.7): reports while the machine moves, at most 10 per second."""

    tag: str
    report: MoveReport
    last_mm: np.ndarray
    since_s: float = 0.0


@dataclass
class SessionState:
    in_session: bool = False
    errors: list[tuple[int, str]] = field(default_factory=list)
    """The errors of severity 2 or more that put the session in its error state (until ClearAllErrors)."""
    aborted: bool = False
    """After AbortE: only ClearAllErrors (6.3.1.5)."""
    report_items: tuple[str, ...] = DEFAULT_PT_MEAS_REPORT
    daemon: Daemon | None = None


class Reply:
    """The ``#`` and ``!`` lines of one transaction, and the errors among them that need ClearAllErrors."""

    def __init__(self, tag: str, method: str) -> None:
        self.tag = tag
        self.method = method
        self.lines: list[bytes] = []
        self.serious: list[tuple[int, str]] = []
        """Errors that put the session in its error state."""
        self.aborts_pending = False
        """An error of severity 2 or more was answered: the pending transactions are aborted (6.2.5)."""

    def data(self, text: str) -> None:
        self.lines.append(line(self.tag, Marker.DATA, text))

    def error(self, code: Code | int, record: bool = True) -> None:
        """An error of this transaction; of severity 2 or more it aborts the pending transactions and (``record``)
        puts the session in its error state; a refusal because of that state (0511, 0514) is not recorded again."""
        self.lines.append(error_line(self.tag, code, self.method or "CommandLine"))
        if severity(code) >= NEEDS_CLEAR:
            self.aborts_pending = True
            if record:
                self.serious.append((int(code), self.method))

    def refuse(self) -> None:
        """6.3.1.7's answer in the error state or after AbortE: 0511 Error processing method, 0514."""
        self.error(Code.ERROR_PROCESSING_METHOD, record=False)
        self.error(Code.USE_CLEAR_ALL_ERRORS, record=False)


def measured_item(item: str, machine: CmmMachine, point: np.ndarray, direction: np.ndarray | None) -> str:
    """One item of a report (6.3.2.6, 6.3.2.11): a position, the probing direction, ER, Q or the head's angles."""
    if item in ("X", "Y", "Z"):
        return f"{item}({number(point['XYZ'.index(item)])})"
    if item == "IJK":
        d = direction if direction is not None else np.zeros(3)
        return f"IJK({number(d[0])}, {number(d[1])}, {number(d[2])})"
    if item == "ER":
        return f"ER({number(machine.ball_radius_mm)})"
    return f"{item}({number(0.0)})"  # Q(): a touch-trigger point is good (0); Tool.A/B/C: a fixed head


IMPLICIT_DIRECTION_MIN_MM = 1e-3
"""PtMeas without IJK, the ball closer to the nominal point than this: no direction (1010)."""


class Handlers:
    """The methods that do not move the machine, and the checks and plans of those that do."""

    def __init__(self, machine: CmmMachine, state: SessionState) -> None:
        self.machine = machine
        self.state = state

    def call(self, cmd: Command, reply: Reply) -> None:
        """Answer a method that does not move the machine (a moving one goes through ``motion_for``)."""
        method = cmd.method
        if method in methods.NO_ARGUMENTS:
            methods.no_arguments(cmd)
        getattr(self, f"_{method}")(cmd, reply)

    # ------------------------------------------------------------------ server methods (6.3.1)

    def _StartSession(self, cmd: Command, reply: Reply) -> None:
        if self.state.in_session:
            reply.error(Code.PROTOCOL_ERROR)  # 6.3.1: a second StartSession
            return
        self.state.in_session = True
        self.state.errors.clear()  # 6.3.1.1: StartSession implicitly executes ClearAllErrors()
        self.state.aborted = False
        self.state.report_items = DEFAULT_PT_MEAS_REPORT
        self.state.daemon = None

    def _EndSession(self, cmd: Command, reply: Reply) -> None:
        self.state.in_session = False  # without a session it does nothing (6.3.1)
        self.state.daemon = None

    def _ClearAllErrors(self, cmd: Command, reply: Reply) -> None:
        self.state.errors.clear()
        self.state.aborted = False

    def _GetErrorInfo(self, cmd: Command, reply: Reply) -> None:
        code = methods.error_number(cmd)
        if code not in ERRORS:
            reply.error(Code.ARGUMENT_OUT_OF_RANGE)
            return
        reply.data(string(ERRORS[code].text))  # 6.3.1.6: the data is a String

    def _GetDMEVersion(self, cmd: Command, reply: Reply) -> None:
        reply.data(f"DMEVersion({string(SPEC_VERSION)})")

    def _StopDaemon(self, cmd: Command, reply: Reply) -> None:
        tag = methods.event_tag(cmd)
        if self.state.daemon is None or self.state.daemon.tag != tag:
            reply.error(Code.DAEMON_DOES_NOT_EXIST)
            return
        self.state.daemon = None

    def _StopAllDaemons(self, cmd: Command, reply: Reply) -> None:
        if self.state.daemon is None:
            reply.error(Code.NO_DAEMONS_ARE_ACTIVE)
        self.state.daemon = None

    # ------------------------------------------------------------------ DME methods (6.3.2)

    def _IsHomed(self, cmd: Command, reply: Reply) -> None:
        reply.data(f"IsHomed({int(self.machine.homed)})")

    def _EnableUser(self, cmd: Command, reply: Reply) -> None:
        self.machine.user_enabled = True

    def _DisableUser(self, cmd: Command, reply: Reply) -> None:
        self.machine.user_enabled = False

    def _IsUserEnabled(self, cmd: Command, reply: Reply) -> None:
        reply.data(f"IsUserEnabled({int(self.machine.user_enabled)})")

    def _GetMachineClass(self, cmd: Command, reply: Reply) -> None:
        reply.data("GetMachineClass(CartCMM)")  # 6.3.2.8: an enumeration since 1.4.3

    def _GetErrStatusE(self, cmd: Command, reply: Reply) -> None:
        reply.data(f"ErrStatus({int(bool(self.state.errors) or self.state.aborted)})")

    def _GetXtdErrStatus(self, cmd: Command, reply: Reply) -> None:
        """6.3.2.10: status lines, then the errors the session is in (reported again, not raised again)."""
        reply.data(f"IsHomed({int(self.machine.homed)})")
        reply.data(f"IsUserEnabled({int(self.machine.user_enabled)})")
        for code, where in self.state.errors:
            reply.lines.append(error_line(reply.tag, code, where))

    def _OnPtMeasReport(self, cmd: Command, reply: Reply) -> None:
        self.state.report_items = tuple(methods.report_items(cmd))

    def _OnMoveReportE(self, cmd: Command, reply: Reply) -> None:
        report = methods.move_report(cmd)
        if self.state.daemon is not None:
            reply.error(Code.DAEMON_ALREADY_EXISTS)
            return
        with self.machine.lock:
            self.state.daemon = Daemon(cmd.tag, report, self.machine.position_mm.copy())

    def _Get(self, cmd: Command, reply: Reply) -> None:
        items = methods.query_items(cmd)
        if not self.machine.tools.active.defined:
            reply.error(Code.TOOL_NOT_DEFINED)
            return
        with self.machine.lock:
            position = self.machine.position_mm.copy()
        reply.data(", ".join(measured_item(item, self.machine, position, None) for item in items))

    # ------------------------------------------------------------------ tools (6.3.2.14 - 6.3.2.23, 6.3.6 - 6.3.13)

    def _EnumTools(self, cmd: Command, reply: Reply) -> None:
        for name in self.machine.tools.enumerate():
            reply.data(string(name))

    def _FindTool(self, cmd: Command, reply: Reply) -> None:
        name = methods.one_string(cmd)
        table = self.machine.tools
        if name == UNDEF_TOOL:
            table.found = table.undefined
            reply.error(Code.TOOL_NOT_DEFINED)
            return
        tool = table.find(name)
        table.found = tool if tool is not None else table.undefined
        if tool is None:
            reply.error(Code.TOOL_NOT_FOUND)  # 6.3.2.16: FoundTool is then UnDefTool

    def tool_to_activate(self, cmd: Command, reply: Reply) -> Tool | None:
        """The tool ChangeTool or SetTool names, or None with the error answered (6.3.2.14's table)."""
        name = methods.one_string(cmd)
        if name == UNDEF_TOOL:
            reply.error(Code.TOOL_NOT_DEFINED)
            return None
        if name == BASE_TOOL:
            reply.error(Code.BAD_ARGUMENT)  # BaseTool is no instance for usage
            return None
        tool = self.machine.tools.find(name)
        if tool is None:
            reply.error(Code.TOOL_NOT_FOUND)
        return tool

    def _SetTool(self, cmd: Command, reply: Reply) -> None:
        tool = self.tool_to_activate(cmd, reply)
        if tool is not None:
            with self.machine.lock:
                self.machine.tools.activate(tool)

    def _owner(self, ref: PropertyRef) -> Tool:
        return self.machine.tools.active if ref.owner == "Tool" else self.machine.tools.found

    def _usable(self, ref: PropertyRef, reply: Reply) -> Tool | None:
        """The tool a property belongs to, None when UnDefTool is asked for a value (1503) or NoTool for its
        PtMeasPar (0507)."""
        tool = self._owner(ref)
        if ref.path in (("Name",), ("AvrRadius",)):
            return tool
        if not tool.defined:
            reply.error(Code.TOOL_NOT_DEFINED)
            return None
        if tool.kind == "none" and ref.path[:1] == ("PtMeasPar",):
            reply.error(Code.ILLEGAL_COMMAND)
            return None
        return tool

    def _value(self, tool: Tool, ref: PropertyRef) -> str:
        if ref.path == ("Name",):
            return string(tool.name)
        if ref.path == ("AvrRadius",):
            return number(tool.ball_radius_mm if tool.can_measure else 0.0)
        parameter = tool.parameter(ref.path[0], ref.path[1])
        return number(parameter.part(ref.path[2] if len(ref.path) == 3 else "Act"))

    def _GetProp(self, cmd: Command, reply: Reply) -> None:
        refs = methods.get_properties(cmd)
        values = []
        with self.machine.lock:
            for ref in refs:
                tool = self._usable(ref, reply)
                if tool is None:
                    return
                values.append(f"{ref.text}({self._value(tool, ref)})")
        reply.data(", ".join(values))

    _GetPropE = _GetProp

    def _SetProp(self, cmd: Command, reply: Reply) -> None:
        """6.3.1.11: every named Act checked first, then set; a value beyond [Min, Max] is clamped, warning 0504."""
        refs = methods.set_properties(cmd)
        with self.machine.lock:
            targets = []
            for ref in refs:
                tool = self._usable(ref, reply)
                if tool is None:
                    return
                targets.append((tool.parameter(ref.path[0], ref.path[1]), ref.value))
            clamped = [parameter.set(float(value)) for parameter, value in targets]
        if any(clamped):
            reply.error(Code.ARGUMENT_OUT_OF_RANGE)

    def _EnumProp(self, cmd: Command, reply: Reply, everything: bool = False) -> None:
        """6.3.1.12, 6.3.1.13: the children's names and types (EnumAllProp: the grandchildren too, named from the
        property asked for, 7.8)."""
        ref = methods.enum_property(cmd)
        tool = self._owner(ref)
        if not tool.defined:
            reply.error(Code.TOOL_NOT_DEFINED)
            return
        if tool.kind == "none" and ref.path[:1] == ("PtMeasPar",):
            reply.error(Code.ILLEGAL_COMMAND)
            return
        for name, kind in _children(tool, ref.path, everything):
            reply.data(f"{string(name)}, {string(kind)}")

    def _EnumAllProp(self, cmd: Command, reply: Reply) -> None:
        self._EnumProp(cmd, reply, everything=True)

    # ------------------------------------------------------------------ CartCMM (6.3.3)

    def _SetCoordSystem(self, cmd: Command, reply: Reply) -> None:
        """Only MachineCsy: hilcal relates the CMM to the rig by the station's alignment, not by part frames."""
        if methods.coord_system(cmd) != "MachineCsy":
            reply.error(Code.ARGUMENT_NOT_SUPPORTED)

    def _GetCoordSystem(self, cmd: Command, reply: Reply) -> None:
        reply.data(f"CoordSystem({self.machine.coord_system})")

    # ------------------------------------------------------------------ moving methods

    def motion_for(self, cmd: Command, reply: Reply, plan: FaultPlan) -> Motion | None:
        """Home, GoTo, PtMeas or ChangeTool: the checked plan, or None with the refusal answered."""
        machine = self.machine
        if cmd.method == Method.HOME:
            methods.no_arguments(cmd)
            return machine.plan_home() if self._free(reply) else None
        if cmd.method == Method.CHANGE_TOOL:
            tool = self.tool_to_activate(cmd, reply)
            if tool is None or not self._free(reply):
                return None
            motion = machine.plan_dwell(machine.config.tool_change_time_s)
            motion.finish.append(lambda: machine.tools.activate(tool))
            return motion
        if cmd.method == Method.GO_TO:
            axes = methods.goto_target(cmd)
            if not machine.homed:
                reply.error(Code.ILLEGAL_COMMAND)
            elif not machine.tools.active.defined:
                reply.error(Code.TOOL_NOT_DEFINED)
            elif machine.out_of_volume(target := machine.target(axes)):
                reply.error(Code.TARGET_OUT_OF_VOLUME)
            elif self._free(reply):
                return machine.plan_goto(target)
            return None
        axes, ijk = methods.ptmeas_target(cmd)
        nominal = machine.target(axes)
        if not machine.homed:
            reply.error(Code.ILLEGAL_COMMAND)
        elif ijk is not None and not np.any(ijk):
            reply.error(Code.VECTOR_HAS_NO_NORM)
        elif machine.out_of_volume(nominal):
            reply.error(Code.TARGET_OUT_OF_VOLUME)
        elif not machine.tools.active.defined:
            reply.error(Code.TOOL_NOT_DEFINED)
        elif not machine.tools.active.can_measure:
            reply.error(Code.ILLEGAL_COMMAND)  # NoTool can only move (6.3.2.14)
        elif self._free(reply):
            with machine.lock:
                vector = np.asarray(ijk, dtype=float) if ijk is not None else machine.position_mm - nominal
            norm = float(np.linalg.norm(vector))
            if norm == 0.0 or (ijk is None and norm < IMPLICIT_DIRECTION_MIN_MM):
                # no IJK: the direction from the nominal point to where the ball is (6.3.2.13); none there
                reply.error(Code.VECTOR_HAS_NO_NORM)
                return None
            return machine.plan_touch(nominal, vector / norm, plan)
        return None

    def _free(self, reply: Reply) -> bool:
        """The machine may move: no emergency stop engaged (else 0500, 9.5)."""
        if self.machine.emergency:
            reply.error(Code.EMERGENCY_STOP)
            return False
        return True

    def report(self, motion: Motion, reply: Reply) -> None:
        """A finished motion's answer: its error, or for PtMeas the report OnPtMeasReport asked for."""
        if motion.error is not None:
            reply.error(motion.error)
        elif motion.measured_mm is not None:
            items = self.state.report_items
            reply.data(", ".join(measured_item(i, self.machine, motion.measured_mm, motion.direction) for i in items))


def _children(tool: Tool, path: tuple[str, ...], everything: bool) -> list[tuple[str, str]]:
    """(name, type) of a tool property's children: blocks, parameters, parameter parts (a part has none)."""
    if len(path) == 3:
        return []
    if len(path) == 2:
        return [(part, "Number") for part in PARAMETER_PARTS]
    if len(path) == 1:
        out = []
        for name in BLOCKS[path[0]]:
            out += [(name, "Number"), (name, "Property")]
            if everything:
                out += [(f"{name}.{part}", "Number") for part in PARAMETER_PARTS]
        return out
    out = []
    for block in BLOCKS:
        if block == "PtMeasPar" and tool.name == NO_TOOL:
            continue
        out.append((block, "Property"))
        if everything:
            out += [(f"{block}.{name}", kind) for name, kind in _children(tool, (block,), True)]
    return [*out, ("Name", "String"), ("AvrRadius", "Number")]

