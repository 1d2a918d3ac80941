"""The simulated CMM's machine, shared by all links: axes, homing, tools, emergency stop and the stylus-ball physics.

Motions are planned at once (``plan_goto``, ``plan_touch``, ...) as straight segments on the machine clock, then run
by ``run`` in samples of machine time (each waited for ``time_scale`` times as long in real time), so that a stop
(AbortE, an emergency stop) halts the ball where it is and move reports follow its way.

PtMeas with the ball of the active tool (6.3.2.13): with n the unit probing direction (IJK, or from the nominal point
to where the ball is), the approach position is nominal + (Approach + r) n; the ball travels there as a GoTo, then
probes along -n at PtMeasPar.Speed towards the end of search, nominal + (r - Search) n, where the ball's surface is
Search beyond the nominal point; at contact it latches the ball's centre (plus noise) and retracts: to contact +
Retract n (Retract >= 0) or back to the approach position (Retract < 0). With no surface within the search it is back
at the approach position and the answer is 1006. Positioning moves (GoTo, approach, retract) that bring the ball into
a sphere are collisions (2504), a ball whose approach position lies inside a sphere an illegal touch (1001); each is
counted and logged as ``cmm_sim.collision``; with ``on_collision = "count"`` only a target inside a sphere stops it.
"""

from __future__ import annotations

import math
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Protocol

import numpy as np
import structlog

from hilcal.protocols.ippdme import Code
from hilcal.robot import Robot
from sim_devices.cmm.config import CmmServerConfig
from sim_devices.cmm.faults import FaultPlan
from sim_devices.cmm.physics import Spheres, sphere_name
from sim_devices.cmm.tools import Tool, ToolTable
from sim_devices.rig.rig import SimulatedRig

log = structlog.get_logger(__name__)

SAMPLE_S = 0.02
"""A running motion is sampled every this much machine time (stops are noticed, move reports taken)."""
MIN_WAIT_S = 0.002
"""The least real time a running motion sleeps at once (``CmmMachine.run``)."""


class MoveListener(Protocol):
    """Told of the machine's position along every motion (a session's OnMoveReportE daemon)."""

    def wants_moves(self) -> bool:
        """True while it needs the motion in samples of machine time; an instant machine (``time_scale`` 0) then
        jumps to each segment's end."""

    def moved(self, position_mm: np.ndarray, dt_s: float) -> None: ...


@dataclass
class Segment:
    end_mm: np.ndarray
    duration_s: float


@dataclass
class Motion:
    """A planned motion: its segments and what it answers once they have all run."""

    segments: list[Segment] = field(default_factory=list)
    error: Code | None = None
    detail: str = ""
    measured_mm: np.ndarray | None = None
    direction: np.ndarray | None = None
    finish: list[Callable[[], None]] = field(default_factory=list)
    """Done when every segment has run (collision counts and logs: a stopped motion never got there)."""

    def move(self, start: np.ndarray, end: np.ndarray, speed_mm_s: float) -> np.ndarray:
        self.segments.append(Segment(end.copy(), float(np.linalg.norm(end - start)) / speed_mm_s))
        return end

    def dwell(self, at: np.ndarray, seconds: float) -> None:
        self.segments.append(Segment(at.copy(), seconds))


class MotionStopped(Exception):
    def __init__(self, reason: str) -> None:
        super().__init__(reason)
        self.reason = reason


class CmmMachine:
    """Position, homing, tools, emergency stop and the touch physics; one per server, shared by its links."""

    def __init__(self, robot: Robot, rig: SimulatedRig, config: CmmServerConfig) -> None:
        self.config = config
        self.spheres = Spheres(robot, rig)
        self.tools = ToolTable(config)
        self.lock = threading.RLock()
        self.motion_lock = threading.Lock()
        """Held while a motion runs: one motion at a time, whichever link asked for it."""
        self.stop_lock = threading.Lock()
        self.motion_stop = threading.Event()
        self.stop_reason = ""
        self.homed = False
        self.user_enabled = True
        self.emergency = False
        self.coord_system = "MachineCsy"
        self.position_mm = np.asarray(config.home_position_mm, dtype=float)
        self.collisions = 0
        """Crashes so far: collisions of positioning moves, illegal touches, platform spheres that struck the ball."""
        self.machine_time_s = 0.0
        """Every motion's duration so far, before ``time_scale``."""
        self.move_listeners: list[MoveListener] = []
        self.event_listeners: list[Callable[[Code, str], None]] = []
        """Sessions told of unsolicited errors (an emergency stop, a platform that struck the ball)."""
        self._rng = np.random.default_rng([config.seed, 0xC33])

    @property
    def ball_radius_mm(self) -> float:
        return self.tools.active.ball_radius_mm

    def broadcast(self, code: Code, where: str) -> None:
        for listener in list(self.event_listeners):
            listener(code, where)

    # ------------------------------------------------------------------ the platform

    def look(self) -> None:
        """Look at the platform: a platform sphere that, since the last look, carried its surface through the homed
        ball struck it (counted, logged; with ``on_collision = "stop"`` an unsolicited 2504 to every session). A ball
        the sphere now covers is left on its surface (pushed aside)."""
        with self.lock:
            _, way = self.spheres.look()
            if way is None or not self.homed:
                return
            struck = self.spheres.strikes(way, self.position_mm, self.ball_radius_mm)
        for index, centre in struck:
            self._strike(index, way[0, index], centre)

    def _strike(self, index: int, c0: np.ndarray, c1: np.ndarray) -> None:
        stop = self.config.on_collision == "stop"
        with self.lock:
            p = self.position_mm.copy()
            self.collisions += 1
            log.warning("cmm_sim.collision", kind="struck", command=None, code=int(Code.COLLISION), stopped=stop,
                        sphere=index, sphere_name=sphere_name(index), from_mm=np.round(c0, 4).tolist(),
                        to_mm=np.round(c1, 4).tolist(), contact_mm=np.round(p, 4).tolist(),
                        collisions=self.collisions)
            reach = self.spheres.radius_mm + self.ball_radius_mm
            gap = p - c1
            dist = float(np.linalg.norm(gap))
            if dist < reach:
                away = gap / dist if dist > 0 else (c0 - c1) / np.linalg.norm(c0 - c1)
                self.position_mm = c1 + reach * away
        if stop:
            self.broadcast(Code.COLLISION, "PlatformStruckProbe")

    # ------------------------------------------------------------------ plans

    def out_of_volume(self, target: np.ndarray) -> bool:
        return bool(np.any(np.abs(target) > self.config.volume_limit_mm))

    def target(self, axes: dict[str, float]) -> np.ndarray:
        """The position with the named axes replaced (an axis not named keeps its value, 6.3.2.12)."""
        with self.lock:
            out = self.position_mm.copy()
        for i, axis in enumerate(("X", "Y", "Z")):
            if axis in axes:
                out[i] = axes[axis]
        return out

    def plan_home(self) -> Motion:
        motion = Motion()
        motion.dwell(np.asarray(self.config.home_position_mm, dtype=float), self.config.home_time_s)
        motion.finish.append(lambda: setattr(self, "homed", True))
        return motion

    def plan_dwell(self, seconds: float) -> Motion:
        motion = Motion()
        motion.dwell(self.position_mm, seconds)
        return motion

    def _collide(self, motion: Motion, kind: str, command: str, start: np.ndarray, end: np.ndarray,
                 contact: tuple[int, np.ndarray], stop: bool, code: Code = Code.COLLISION) -> None:
        """A positioning move whose ball meets a sphere: counted and logged once the machine gets there; ``stop``
        ends the motion at the contact with ``code``."""
        index, point = contact

        def record() -> None:
            with self.lock:
                self.collisions += 1
                log.warning("cmm_sim.collision", kind=kind, command=command, code=int(code), stopped=stop,
                            sphere=index, sphere_name=sphere_name(index), from_mm=np.round(start, 4).tolist(),
                            to_mm=np.round(end, 4).tolist(), contact_mm=np.round(point, 4).tolist(),
                            collisions=self.collisions)

        motion.finish.append(record)
        if stop:
            motion.move(start, point, self._travel_speed())
            motion.error, motion.detail = code, f"{kind} met {sphere_name(index)}"

    def _travel_speed(self, tool: Tool | None = None) -> float:
        return (tool or self.tools.active).travel_speed_mm_s

    def plan_goto(self, target: np.ndarray) -> Motion:
        """GoTo: the ball straight to ``target`` (a path into a sphere stops there with 2504, or with
        ``on_collision = "count"`` is counted and passed, unless the target itself is inside)."""
        motion = Motion()
        with self.lock:
            start, r = self.position_mm.copy(), self.ball_radius_mm
        centres = self.spheres.centres_mm()  # a motion is planned at one instant: one look at the platform
        contact = self.spheres.first_contact(start, target, r, centres)
        if contact is not None:
            stop = self.config.on_collision == "stop" or self.spheres.inside(target, r, centres) is not None
            self._collide(motion, "goto", "GoTo", start, target, contact, stop)
            if stop:
                return motion
        motion.move(start, target, self._travel_speed())
        return motion

    def plan_touch(self, nominal: np.ndarray, direction: np.ndarray, plan: FaultPlan) -> Motion:
        """PtMeas with the active tool's ball along the unit ``direction`` (6.3.2.13; see the module's docstring)."""
        tool = self.tools.active
        motion = Motion(direction=direction)
        with self.lock:
            start = self.position_mm.copy()
        r = tool.ball_radius_mm
        approach = nominal + (tool.approach_mm + r) * direction
        end_of_search = nominal + (r - tool.search_mm) * direction
        centres = self.spheres.centres_mm()  # a motion is planned at one instant: one look at the platform
        contact = self.spheres.first_contact(start, approach, r, centres)
        if self.spheres.inside(approach, r, centres) is not None:
            assert contact is not None
            self._collide(motion, "illegal_touch", "PtMeas", start, approach, contact, True, Code.ILLEGAL_TOUCH)
            return motion
        if contact is not None:
            stop = self.config.on_collision == "stop"
            self._collide(motion, "approach", "PtMeas", start, approach, contact, stop)
            if stop:
                return motion
        at = motion.move(start, approach, tool.travel_speed_mm_s)
        stroke = tool.approach_mm + tool.search_mm
        touched = self.spheres.touch(approach, -direction, stroke, r, centres)
        if plan.miss or touched is None:
            at = motion.move(at, end_of_search, tool.probing_speed_mm_s)
            motion.dwell(at, self.config.probe_time_s)
            motion.move(at, approach, tool.travel_speed_mm_s)
            motion.error = Code.SURFACE_NOT_FOUND
            motion.detail = "injected miss" if plan.miss else "no surface within the search"
            return motion
        centre = approach - touched[1] * direction
        at = motion.move(approach, centre, tool.probing_speed_mm_s)
        motion.dwell(at, self.config.probe_time_s)
        measured = centre + self._rng.normal(0.0, self.config.noise_sigma_mm, 3)
        if plan.outlier:
            measured = measured + self.config.outlier_mm * direction
        motion.measured_mm = measured
        back = centre + tool.retract_mm * direction if tool.retract_mm >= 0 else approach
        contact = self.spheres.first_contact(centre, back, r, centres)
        if contact is not None:
            stop = self.config.on_collision == "stop"
            self._collide(motion, "retract", "PtMeas", centre, back, contact, stop)
            if stop:
                motion.measured_mm = None
                return motion
        motion.move(centre, back, tool.travel_speed_mm_s)
        return motion

    # ------------------------------------------------------------------ running

    def request_stop(self, reason: str) -> None:
        """Stop the running motion as soon as possible (``abort`` or ``emergency``)."""
        with self.stop_lock:
            self.stop_reason = reason
            self.motion_stop.set()

    def run(self, motion: Motion, wait: Callable[[float], bool]) -> None:
        """Run a motion's segments on the machine clock; ``wait(seconds)`` sleeps and is True when the server
        stops. MotionStopped if a stop was requested meanwhile (the ball stays where it got to).

        Each sample is due ``time_scale`` times its machine time after the motion's start, real time; a sample due
        less than MIN_WAIT_S ahead is taken at once (a sleep of microseconds costs its timer slack, tens of times its
        length), so the motion lasts its scaled machine time, not its samples' slack."""
        scale = self.config.time_scale
        started, due_s = time.monotonic(), 0.0
        last = len(motion.segments) - 1
        for index, segment in enumerate(motion.segments):
            with self.lock:
                start = self.position_mm.copy()
            sampled = scale > 0 or any(listener.wants_moves() for listener in list(self.move_listeners))
            steps = max(1, math.ceil(segment.duration_s / SAMPLE_S)) if sampled else 1
            dt = segment.duration_s / steps
            for k in range(1, steps + 1):
                due_s += dt * scale
                ahead_s = started + due_s - time.monotonic()
                final = index == last and k == steps
                if ahead_s > 0 and (ahead_s >= MIN_WAIT_S or final) and wait(ahead_s):
                    raise MotionStopped("server")
                if self.motion_stop.is_set():
                    raise MotionStopped(self.stop_reason)
                with self.lock:
                    self.position_mm = start + (segment.end_mm - start) * (k / steps)
                    self.machine_time_s += dt
                    position = self.position_mm.copy()
                for listener in list(self.move_listeners):
                    listener.moved(position, dt)
        for done in motion.finish:
            done()
