"""Riding through short link drop-outs: hold, check, re-take; end the run only when a link stays down.

A heartbeat later than the driver's ``heartbeat_timeout_s`` means the link is down *for now*: the driver refuses
every command but the e-stop, so nothing moves. The guard then holds (bounded by the grace period counted from
the last heartbeat), re-reads the controller when heartbeats return, refuses to go on after a fault or an
e-stop, checks the platform is where it was told to be, and re-takes the interrupted pose from its approach
point (every leg shorter by the approach distance) so the pose is still reached with every leg extending.
The measuring instrument's link errors (a CMM's or a laser tracker's: silence beyond the driver's own resends, a
stream out of step, a lost connection) and Modbus errors get a bounded number of retries of the same (idempotent)
message after a short wait. An error the instrument reports (a target not found, a registration that fails) is no
link problem: it ends the run with the instrument's reason. Every hold, retry and loss is journaled; `links_summary`
turns the journal into the report's per-link lines (the CMM's link is "cmm", the laser tracker's "tracker").
"""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import Any

import numpy as np
import structlog
from pydantic import BaseModel, ConfigDict, Field, model_validator

from drivers.cmm.base import CmmConnectionError, CmmProtocolError, CmmTimeout
from drivers.controller.base import CommandTimeout, ControllerLost
from drivers.controller.modbus import ModbusTransportError
from drivers.tracker.base import TrackerConnectionError, TrackerProtocolError, TrackerTimeout
from hilcal.protocols.controller_states import MOTION_STATES, ControllerState
from procedures import messages as m
from procedures.journal import Journal

log = structlog.get_logger(__name__)

LINKS = ("controller", "cmm", "tracker", "modbus")
INSTRUMENT_LINKS = ("cmm", "tracker")


class LinksSection(BaseModel):
    """The station's ``[links]``: how long and how often a run rides through a link that drops out."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    heartbeat_grace_s: float = Field(default=1.0, gt=0, le=60,
                                     description="controller lost only after this long without a heartbeat, s")
    holds_per_message: int = Field(default=5, ge=0, le=100, description="holds of one message before the run ends")
    cmm_retries: int = Field(default=2, ge=0, le=10, description="new measurements after the driver's own retries")
    cmm_wait_s: float = Field(default=1.0, ge=0, le=60, description="wait before a CMM retry, s")
    tracker_retries: int = Field(default=2, ge=0, le=10, description="new measurements after the tracker driver's "
                                 "own new connections")
    tracker_wait_s: float = Field(default=1.0, ge=0, le=60, description="wait before a tracker retry, s")
    modbus_retries: int = Field(default=3, ge=0, le=10, description="new attempts of a Modbus step after a drop")
    modbus_wait_s: float = Field(default=0.5, ge=0, le=60, description="wait before a Modbus retry, s")

    @model_validator(mode="after")
    def _grace_above_jitter(self) -> LinksSection:
        if self.heartbeat_grace_s < 0.2:
            raise ValueError(f"heartbeat_grace_s ({self.heartbeat_grace_s}) must be at least 0.2 s: a grace "
                             "period near scheduler jitter turns a busy computer into a lost controller")
        return self


class LinkLost(RuntimeError):
    """A link stayed down beyond its grace period or its retries; the run ends with the journal intact."""


class PlatformUnsafe(RuntimeError):
    """After a hold the controller reports a fault or an e-stop: the run ends; a person must look first."""


def _link_of(error: BaseException) -> str | None:
    if isinstance(error, ControllerLost | CommandTimeout):
        return "controller"
    if isinstance(error, CmmTimeout | CmmProtocolError | CmmConnectionError):
        return "cmm"
    if isinstance(error, TrackerTimeout | TrackerProtocolError | TrackerConnectionError):
        return "tracker"
    if isinstance(error, ModbusTransportError):
        return "modbus"
    return None


class LinkGuard:
    """Runs one engine message at a time through `run`, holding and retrying on transient link errors."""

    def __init__(self, devices: Any, journal: Journal, links: LinksSection | None = None, *,
                 approach_mm: float = 0.5, move_timeout_s: float = 120.0,
                 publish: Callable[..., None] | None = None) -> None:
        self.devices = devices
        self.journal = journal
        self.links = links or LinksSection()
        self.approach_mm = approach_mm
        self.move_timeout_s = move_timeout_s
        self.publish = publish or (lambda kind, **data: None)
        self.last_target: np.ndarray | None = None

    def run(self, msg: object, dispatch: Callable[[object], Any]) -> Any:
        """dispatch(msg), riding through transient link errors; LinkLost or PlatformUnsafe when it cannot."""
        tries = {link: 0 for link in LINKS}
        retake: np.ndarray | None = None
        while True:
            try:
                if retake is not None:
                    self._retake(msg, retake)
                    retake = None
                result = dispatch(msg)
            except Exception as error:
                link = _link_of(error)
                if link is None:
                    raise
                tries[link] += 1
                retake = self._hold(link, msg, error, tries[link])
                continue
            if isinstance(msg, m.MoveLegs):
                self.last_target = np.asarray(msg.lengths_mm, dtype=float)
            return result

    def _limit(self, link: str) -> int:
        return {"controller": self.links.holds_per_message, "cmm": self.links.cmm_retries,
                "tracker": self.links.tracker_retries, "modbus": self.links.modbus_retries}[link]

    def _hold(self, link: str, msg: object, error: BaseException, attempt: int) -> np.ndarray | None:
        """Journal, wait for the link (bounded), check it; the leg lengths read if the pose must be re-taken."""
        what = type(msg).__name__
        reason = f"{type(error).__name__}: {error}"
        if attempt > self._limit(link):
            self._lost(link, what, f"still failing after {attempt - 1} retries ({reason})")
        t0 = time.monotonic()
        self.journal.event("link_hold", link=link, message=what, attempt=attempt, error=reason)
        log.warning("link_hold", link=link, message=what, attempt=attempt, error=reason)
        self.publish("held", link=link, message=what, error=reason)
        lengths = None
        if link == "controller":
            lengths = self._recover_controller(msg, reason)
        else:
            time.sleep({"cmm": self.links.cmm_wait_s, "tracker": self.links.tracker_wait_s}.get(
                link, self.links.modbus_wait_s))
        held_s = time.monotonic() - t0
        self.journal.event("link_recovered", link=link, message=what, attempt=attempt, held_s=held_s)
        log.info("link_recovered", link=link, message=what, held_s=round(held_s, 3))
        self.publish("recovered", link=link, message=what, held_s=held_s)
        return lengths

    def _lost(self, link: str, what: str, why: str) -> None:
        self.journal.event("link_lost", link=link, message=what, reason=why)
        raise LinkLost(f"{link} link lost during {what}: {why}")

    def _recover_controller(self, msg: object, reason: str) -> np.ndarray | None:
        """Wait for heartbeats (bounded by the grace period) and check the state; the lengths if moving is safe."""
        controller = self.devices.controller
        grace = self.links.heartbeat_grace_s
        age = controller.heartbeat_age_s
        remaining = grace - (age if age is not None else 0.0)
        try:
            if remaining <= 0:
                raise ControllerLost(f"last heartbeat {age:.3f} s ago")
            feedback = controller.wait_for_heartbeat(remaining)
        except ControllerLost as e:
            self._lost("controller", type(msg).__name__,
                       f"no heartbeat within the {grace:.2f} s grace period ({e}; first: {reason})")
        if feedback.state in (ControllerState.FAULT, ControllerState.ESTOP):
            self.journal.event("link_unsafe", link="controller", state=feedback.state.name,
                               fault=feedback.fault.name)
            raise PlatformUnsafe(f"after the link returned the controller is {feedback.state.name} "
                                 f"(fault {feedback.fault.name}): nothing is moved; check the machine")
        if feedback.state in MOTION_STATES and isinstance(msg, m.MoveLegs | m.Settle | m.Measure):
            return np.asarray(feedback.lengths_mm, dtype=float)
        return None

    def _retake(self, msg: object, lengths: np.ndarray) -> None:
        """Back to the pose's approach point, then (unless msg is the move itself) to the pose again.

        The approach point is held within the legs' travel: an interrupted move that was itself an approach (the
        plan keeps those at least 1 mm above the lower limit) would otherwise be re-taken from below the limit, a
        setpoint the controller refuses, which stops the run."""
        target = np.asarray(msg.lengths_mm, dtype=float) if isinstance(msg, m.MoveLegs) else self.last_target
        if target is None:
            return
        off_mm = float(np.max(np.abs(lengths - target)))
        if not isinstance(msg, m.MoveLegs) and off_mm <= self.devices.station.motion.position_tolerance_mm:
            self.journal.event("link_position_checked", off_mm=off_mm)
            return
        self.journal.event("link_retake", message=type(msg).__name__, off_mm=off_mm,
                           approach_mm=self.approach_mm)
        controller = self.devices.controller
        lowest_mm = self.devices.robot.leg_limits[0]
        controller.move_legs(np.maximum(target - self.approach_mm, lowest_mm), self.move_timeout_s)
        if not isinstance(msg, m.MoveLegs):
            controller.move_legs(target, self.move_timeout_s)


def links_summary(journal: Journal) -> dict[str, dict[str, Any]]:
    """Per link: holds, retakes, total and longest hold (s), and whether it was lost (over the whole journal); of the
    instrument links the one the run used (the tracker's when it was made ready, else the CMM's)."""
    used = "tracker" if journal.count_events("tracker_ready") else "cmm"
    out = {link: {"holds": 0, "held_s": 0.0, "longest_hold_s": 0.0, "retakes": 0, "lost": False}
           for link in LINKS if link not in INSTRUMENT_LINKS or link == used}
    for event in journal.events("link_hold", "link_recovered", "link_lost", "link_retake"):
        data = event["data"]
        link = data.get("link", "controller")
        if link not in out:
            continue
        if event["kind"] == "link_hold":
            out[link]["holds"] += 1
        elif event["kind"] == "link_recovered":
            out[link]["held_s"] += float(data["held_s"])
            out[link]["longest_hold_s"] = max(out[link]["longest_hold_s"], float(data["held_s"]))
        elif event["kind"] == "link_retake":
            out[link]["retakes"] += 1
        else:
            out[link]["lost"] = True
    return out
