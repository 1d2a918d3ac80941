"""The CMM driver: I++ DME 1.4.3 over the transport its URL names (``socket://host:1294``, the standard's TCP, 6.1;
a serial line or pty otherwise), on the transaction layer of ``drivers.cmm.link``.

What it sends and when (docs/protocols.md, CMM section):

* ``start_session``: StartSession (0008 when a session is open already: ClearAllErrors, EndSession, StartSession,
  6.3.1), GetDMEVersion (0501 before 1.4: noted), GetMachineClass, SetCoordSystem(MachineCsy) (the station's
  alignment is in the machine's frame), EnumTools, GetProp(Tool.Name());
* ``home``: IsHomed, Home only when not homed (or when asked), ChangeTool to the station's tool when another is
  active (GetChangeToolAction first, for the log; the active tool asked after it, 6.3.2.18), then the stylus:
  GetProp(Tool.AvrRadius()) (6.3.13: the ball radius comes from the CMM), OnPtMeasReport(X(), Y(), Z(), IJK(), ER())
  falling back to IJK() and then X, Y, Z where the server refuses, the PtMeasPar limits and settings, and the
  position, Get(X(), Y(), Z());
* a touch: SetProp of Approach, Search and Retract when they change, read back with GetProp (a server clamps, 6.3.7);
  PtMeas(X(), Y(), Z(), IJK()) with the nominal surface point; after a miss (1006) ClearAllErrors and Get(X(), Y(),
  Z()), the specification defining no position there.

A motion (GoTo, PtMeas, Home, ChangeTool) is never sent twice: when it does not complete in time, AbortE (an E-tag,
6.3.1.5) stops it, the aborted transactions' responses and AbortE's ``%`` are collected, ClearAllErrors, then
GetErrStatusE, GetXtdErrStatus and Get(X(), Y(), Z()) tell the error state and where the ball is: the caller gets
``CmmMotionTimeout`` with that position, or the result when the motion had completed after all. Queries that move
nothing are asked again (``drivers.cmm.link.RE_ASKABLE``). An error of severity 2 or more raises its typed error
(``CmmEmergencyStop``, ``CmmCollision``, ``ProbeMiss``...; warnings are logged and returned); an unsolicited one
(E0000) stops the operation, and nothing but the commands of 6.2.5 is sent until ``clear_errors()``.
"""

from __future__ import annotations

from typing import Literal

import numpy as np
import structlog
from pydantic import Field

from drivers.cmm import answers
from drivers.cmm.base import CmmInterface
from drivers.cmm.link import IppLink, LinkConfig, LinkGarbled, LinkTimeout, Transaction, raise_for
from drivers.cmm.transcript import TranscriptSink
from drivers.cmm.types import (
    CmmConnectionError,
    CmmDriverError,
    CmmError,
    CmmInErrorState,
    CmmMotionTimeout,
    CmmProtocolError,
    CmmToolChanged,
    ProbeLost,
    ProbingConfig,
    Touch,
    TouchSettings,
)
from drivers.cmm.wire import Arg, Item, Word
from hilcal.protocols.ippdme import NEEDS_CLEAR, NO_TOOL, PT_MEAS_PAR, UNDEF_TOOL, Code, Method

log = structlog.get_logger(__name__)

REPORTS = (["X", "Y", "Z", "IJK", "ER"], ["X", "Y", "Z", "IJK"], ["X", "Y", "Z"])
"""What a touch is asked to report, best first (6.3.2.6): the server's refusal of one tries the next."""
TOUCH_PARAMETERS = ("Approach", "Search", "Retract")


class IppDmeConfig(LinkConfig):
    """The driver's settings: the link's timing, the motions' waits, homing and a fallback stylus radius."""

    motion_timeout_s: float = Field(default=60.0, gt=0, description="from '&' to '%' of GoTo and PtMeas")
    home_timeout_s: float = Field(default=300.0, gt=0, description="from '&' to '%' of Home and ChangeTool")
    home: Literal["if_needed", "always"] = Field(default="if_needed", description="Home only when IsHomed says 0")
    stylus_radius_mm: float | None = Field(default=None, gt=0, description="the ball radius, used only when the CMM "
                                           "does not answer Tool.AvrRadius() (a server before 1.4.3)")


def _xyz(point: np.ndarray) -> tuple[Item, Item, Item]:
    p = np.asarray(point, dtype=float)
    if p.shape != (3,) or not np.all(np.isfinite(p)):
        raise ValueError(f"a point is 3 finite numbers, got {point!r}")
    return Item("X", (float(p[0]),)), Item("Y", (float(p[1]),)), Item("Z", (float(p[2]),))


class IppDmeCmm(CmmInterface):
    """A CMM speaking I++ DME 1.4.3. Construct with a URL; ``start_session()`` and ``home()`` before probing."""

    def __init__(self, url: str, config: IppDmeConfig | None = None, probing: ProbingConfig | None = None,
                 transcript: TranscriptSink | None = None, tool: str | None = None) -> None:
        self.config = config or IppDmeConfig()
        self.probing = probing or ProbingConfig()
        self.tool = tool
        """The stylus the station names (None: the active one)."""
        self.link = IppLink(url, self.config, transcript)
        self.url = self.link.url
        self.version: str | None = None
        self.machine_class: str | None = None
        self.tools: list[str] = []
        self.active_tool: str | None = None
        self.report_items: list[str] = list(REPORTS[-1])
        self.limits: dict[str, float] = {}
        """The CMM's Min and Max of the touch settings (``Approach.Max``...), where it states them."""
        self._events_seen = 0
        self._in_session = False

    def close(self) -> None:
        """End the session if one is open (6.3.1.2: then the client may close the connection; a serial CMM cannot
        tell that its client went away), and close the connection."""
        if self._in_session and self.is_open:
            try:
                self.end_session()
            except CmmDriverError as err:
                log.warning("cmm.end_session_failed", error=str(err))
        self.link.close()

    @property
    def is_open(self) -> bool:
        """The connection is open."""
        return bool(self.link._port.is_open)

    # ------------------------------------------------------------------ transactions

    def _query(self, method: str, *args: Arg) -> Transaction:
        """A command that moves nothing (asked again after a timeout where ``RE_ASKABLE`` allows)."""
        return self.link.transact(method, *args)

    def _motion(self, method: str, *args: Arg, timeout_s: float | None = None) -> Transaction:
        """A command that moves the machine: sent once; a timeout is recovered with AbortE (module docstring)."""
        self._events()
        tx = self.link.send(method, *args)
        try:
            self.link.wait(tx, self.config.motion_timeout_s if timeout_s is None else timeout_s)
        except (LinkTimeout, LinkGarbled) as err:
            return self._recover(tx, err)
        return self.link.outcome(tx)

    def _recover(self, tx: Transaction, err: Exception) -> Transaction:
        log.warning("cmm.motion_timeout", command=tx.line, error=str(err))
        self.position_mm = None
        abort = self.link.send(Method.ABORT_E)
        try:
            self.link.wait(abort, self.config.abort_timeout_s)
        except (LinkTimeout, LinkGarbled) as err2:
            raise CmmConnectionError(f"{tx.line} did not complete and AbortE was not answered within "
                                     f"{self.config.abort_timeout_s} s: the link or the CMM is down; where the "
                                     "stylus is is unknown and nothing more is sent") from err2
        if not tx.done:
            log.warning("cmm.abort_left_transaction_open", command=tx.line)
            self.link.abandon(tx)
        self.link.transact(Method.CLEAR_ALL_ERRORS)
        status: bool | None = None
        try:
            status = answers.flag(self.link.transact(Method.GET_ERR_STATUS_E), "ErrStatus")
            xtd = self.link.transact(Method.GET_XTD_ERR_STATUS)
            log.warning("cmm.error_status_after_abort", in_error=status, status=[d.raw for d in xtd.data])
            position = self._where()
        except CmmDriverError as err3:
            log.error("cmm.position_unknown_after_abort", error=str(err3))
            position = None
        self.position_mm = position
        stopped = [e for e in tx.unsolicited if e.severity >= NEEDS_CLEAR]
        if stopped:  # an emergency stop came meanwhile: it is what the caller gets, and nothing moves until cleared
            self.link.error_state = raise_for(stopped, tuple(stopped))
            raise self.link.error_state from err
        if status:
            self.link.error_state = CmmError(Code.MACHINE_IN_ERROR_STATE, "Machine in error state", 3,
                                             Method.GET_ERR_STATUS_E, tx.tag)
        completed = tx.done and not tx.garbled and not any(e.severity >= NEEDS_CLEAR for e in tx.errors)
        if completed:
            log.warning("cmm.motion_completed_late", command=tx.line)
            return self.link.outcome(tx)
        where = "unknown" if position is None else f"at {np.round(position, 4).tolist()} mm"
        raise CmmMotionTimeout(f"{tx.line}: not completed in time; aborted with AbortE (not sent again), errors "
                               f"cleared; the stylus is {where}", tx.line, position, status) from err

    def _events(self) -> None:
        """Take in the server's events since the last look: a tool it changed (9.5.4) or a property it set (9.5.5)."""
        self.link.poll()
        new = min(self.link.events_total - self._events_seen, len(self.link.events))
        self._events_seen = self.link.events_total
        for ev in list(self.link.events)[len(self.link.events) - new:]:
            it = next(iter(ev.line.items().values()), None)
            if it is None:
                continue
            if it.name == "ChangeTool":
                self.stylus_radius_mm, self.touch, self.active_tool = None, None, str(it.args[0])
                raise CmmToolChanged(f"the CMM changed its tool to {it.args[0]!r} on its own (E0000 ChangeTool, "
                                     "9.5.4): the stylus is read again before the next measurement")
            if it.name == "SetProp":
                self.touch = None
                log.warning("cmm.property_set_by_server", line=ev.line.raw)

    # ------------------------------------------------------------------ session, identity, tool, stylus

    def _start_session(self) -> None:
        self._in_session = True
        try:
            self._query(Method.START_SESSION)
        except CmmError as err:
            if err.code != Code.PROTOCOL_ERROR:
                raise
            log.warning("cmm.session_was_open", error=str(err))
            self.clear_errors()
            self._query(Method.END_SESSION)
            self._query(Method.START_SESSION)
        try:
            self.version = answers.string_item(self._query(Method.GET_DME_VERSION), "DMEVersion")
        except CmmError as err:
            if err.code != Code.UNSUPPORTED_COMMAND:
                raise
            self.clear_errors()
            log.warning("cmm.version_before_1_4", note="GetDMEVersion unsupported (6.3.1.14)")
        self.machine_class = answers.machine_class(self._query(Method.GET_MACHINE_CLASS), self.link.note)
        self._query(Method.SET_COORD_SYSTEM, Word("MachineCsy"))
        self.tools = answers.strings(self._query(Method.ENUM_TOOLS))
        self.active_tool = answers.string_item(self._query(Method.GET_PROP, Item("Tool.Name")), "Tool.Name")
        self._events_seen = self.link.events_total
        log.info("cmm.identity", url=self.url, version=self.version, machine_class=self.machine_class,
                 tools=self.tools, active_tool=self.active_tool)

    def end_session(self) -> None:
        self._in_session = False
        self._query(Method.END_SESSION)

    def is_homed(self) -> bool:
        """Whether the CMM's axes are homed (6.3.2.2); nothing moves."""
        return answers.flag(self._query(Method.IS_HOMED), "IsHomed")

    def _home(self, force: bool) -> np.ndarray:
        homed = self.is_homed()
        if force or not homed or self.config.home == "always":
            self._motion(Method.HOME, timeout_s=self.config.home_timeout_s)
        if self.tool is not None and self.tool != self.active_tool:
            self._change_tool(self.tool)
        self.stylus_radius_mm = self._refresh_stylus()
        return self._where()

    def _change_tool(self, name: str) -> None:
        if name not in self.tools:
            raise CmmDriverError(f"the CMM has no tool {name!r}: EnumTools lists {', '.join(self.tools) or 'none'}")
        try:
            action = self._query(Method.GET_CHANGE_TOOL_ACTION, name)
            log.info("cmm.change_tool_action", tool=name, action=[d.raw for d in action.data])
        except CmmError as err:
            self.clear_errors()
            log.info("cmm.change_tool_action_unknown", tool=name, error=str(err))
        self.position_mm = None
        try:
            self._motion(Method.CHANGE_TOOL, name, timeout_s=self.config.home_timeout_s)
        finally:
            if self.link.error_state is not None:
                self.clear_errors()
            self.active_tool = answers.string_item(self._query(Method.GET_PROP, Item("Tool.Name")), "Tool.Name")
        if self.active_tool != name:
            raise CmmDriverError(f"ChangeTool({name!r}) completed but the active tool is {self.active_tool!r}")
        self.stylus_radius_mm, self.touch, self._touch_request = None, None, None

    def _refresh_stylus(self) -> float:
        if self.active_tool in (NO_TOOL, UNDEF_TOOL):
            listed = ", ".join(self.tools) or "none"
            raise CmmDriverError(f"the active tool is {self.active_tool}: it cannot measure (6.3.2.14); name the "
                                 f"stylus in the station's [cmm] tool (the CMM lists {listed})")
        try:
            radius = answers.numbers(self._query(Method.GET_PROP, Item("Tool.AvrRadius")), ["Tool.AvrRadius"],
                                     self.link.note)["Tool.AvrRadius"]
        except CmmError as err:
            self.clear_errors()
            if self.config.stylus_radius_mm is None:
                raise CmmDriverError(f"the CMM does not state its stylus radius (GetProp(Tool.AvrRadius()), 6.3.13, "
                                     f"{err}); for a server before 1.4.3 give it as [cmm.ippdme] "
                                     "stylus_radius_mm") from err
            radius = self.config.stylus_radius_mm
            log.warning("cmm.stylus_radius_from_configuration", radius_mm=radius, error=str(err))
        if not radius > 0:
            raise CmmDriverError(f"the active tool {self.active_tool!r} states no tip radius (AvrRadius {radius}): "
                                 "not a ball stylus, it cannot touch tooling spheres")
        self._report_format()
        self._read_touch()
        log.info("cmm.stylus", tool=self.active_tool, radius_mm=radius, reports=self.report_items,
                 touch=None if self.touch is None else vars(self.touch), limits=self.limits)
        return float(radius)

    def _report_format(self) -> None:
        for items in REPORTS:
            try:
                self._query(Method.ON_PT_MEAS_REPORT, *(Item(n) for n in items))
            except CmmError as err:
                self.clear_errors()
                log.info("cmm.report_refused", items=items, error=str(err))
                continue
            self.report_items = list(items)
            return
        raise CmmDriverError("the CMM refuses OnPtMeasReport(X(), Y(), Z()) (6.3.2.6)")

    def _read_touch(self) -> None:
        names = [f"{PT_MEAS_PAR}.{p}.{part}" for p in TOUCH_PARAMETERS for part in ("Min", "Max")]
        try:
            self.limits = answers.numbers(self._query(Method.GET_PROP, *(Item(n) for n in names)), names,
                                          self.link.note)
        except CmmError as err:
            self.clear_errors()
            self.limits = {}
            log.info("cmm.touch_limits_unknown", error=str(err))
        self.touch, self._touch_request = self._get_touch(), None

    def _get_touch(self) -> TouchSettings:
        names = [f"{PT_MEAS_PAR}.{p}" for p in TOUCH_PARAMETERS]
        values = answers.numbers(self._query(Method.GET_PROP, *(Item(n) for n in names)), names, self.link.note)
        return TouchSettings(*(values[n] for n in names))

    def _within_limits(self, approach_mm: float, search_mm: float) -> tuple[float, float]:
        def clamp(value: float, name: str) -> float:
            low = self.limits.get(f"{PT_MEAS_PAR}.{name}.Min", -np.inf)
            high = self.limits.get(f"{PT_MEAS_PAR}.{name}.Max", np.inf)
            return float(min(max(value, low), high))

        return clamp(approach_mm, "Approach"), clamp(search_mm, "Search")

    def _set_touch(self, approach_mm: float, search_mm: float, retract_mm: float) -> TouchSettings:
        asked = dict(zip(TOUCH_PARAMETERS, (approach_mm, search_mm, retract_mm), strict=True))
        tx = self._query(Method.SET_PROP, *(Item(f"{PT_MEAS_PAR}.{k}", (v,)) for k, v in asked.items()))
        got = self._get_touch()
        if tx.warnings or got != TouchSettings(approach_mm, search_mm, retract_mm):
            log.warning("cmm.touch_settings_clamped", asked=asked, got=vars(got),
                        warnings=[(w.code, w.text) for w in tx.warnings])
        return got

    def error_info(self, code: int) -> str:
        """GetErrorInfo (6.3.1.6): the CMM's text for an error number (its data is a String)."""
        texts = answers.strings(self._query(Method.GET_ERROR_INFO, float(code)))
        if len(texts) != 1:
            raise CmmProtocolError(f"GetErrorInfo({code}) answered {len(texts)} Strings, expected 1")
        return texts[0]

    def clear_errors(self) -> None:
        """ClearAllErrors (6.3.1.7), then GetErrStatusE: CmmInErrorState if the CMM stays in error (an emergency
        stop still pressed)."""
        self.link.transact(Method.CLEAR_ALL_ERRORS)
        if answers.flag(self.link.transact(Method.GET_ERR_STATUS_E), "ErrStatus"):
            raise CmmInErrorState("the CMM is still in error after ClearAllErrors (GetErrStatusE answers 1)",
                                  self.link.error_state)

    # ------------------------------------------------------------------ motion and touches

    def _where(self) -> np.ndarray:
        tx = self._query(Method.GET, *(Item(n) for n in "XYZ"))
        return answers.xyz(answers.positions(answers.one_line(tx), ["X", "Y", "Z"], self.link.note))

    def _goto(self, point_mm: np.ndarray) -> None:
        self._motion(Method.GO_TO, *_xyz(point_mm))

    def _probe(self, nominal_mm: np.ndarray, ijk: np.ndarray) -> Touch:
        n = np.asarray(ijk, dtype=float)
        try:
            tx = self._motion(Method.PT_MEAS, *_xyz(nominal_mm), Item("IJK", tuple(float(v) for v in n)))
        except CmmProtocolError as err:
            if isinstance(err, CmmMotionTimeout | CmmToolChanged):
                raise
            raise ProbeLost(f"PtMeas at {np.round(nominal_mm, 4).tolist()}: the report was garbled ({err})") from err
        try:
            values = answers.positions(answers.one_line(tx), self.report_items, self.link.note)
        except CmmProtocolError as err:
            raise ProbeLost(f"PtMeas at {np.round(nominal_mm, 4).tolist()}: {err}") from err
        ijk_reported = np.array(values["IJK"]) if "IJK" in values and len(values["IJK"]) == 3 else None
        er = values["ER"][0] if "ER" in values else None
        log.debug("cmm.touch", nominal_mm=nominal_mm.tolist(), ijk=n.tolist(), centre_mm=answers.xyz(values).tolist(),
                  effective_radius_mm=er)
        return Touch(answers.xyz(values), ijk_reported, er)
