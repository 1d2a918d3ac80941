"""The simulated CMM's machine and protocol session: touch physics, collisions, homing, error state, responses.

Physics: the six tooling spheres of the SimulatedRig (platform spheres moving with ``rig.true_pose()``, base
spheres fixed) expressed in the CMM frame with ``rig.to_cmm``. ``PtMeas(X,Y,Z,IJK)`` moves the probe from
target + s*IJK along -IJK for up to 2*s (s = search distance) and returns the first surface touched plus
Gaussian noise; no surface on that path is error 1006 "Surface not found". Every positioning move is a straight
line from where the probe is (its tip a point): a ``GoTo`` or a PtMeas approach that enters a sphere crashes
(error 2504 Collision; a PtMeas start point inside a sphere is 1001 Illegal touch), and the probe stops where it
met the surface. The machine also notices when the platform has moved (at every command, and whenever it asks for
the sphere centres): a platform sphere whose way from its old to its new centre (the poses between interpolated:
translation straight, orientation by slerp) passes through the homed probe has struck it (kind "struck"; with
``on_collision = "stop"`` it latches error 2504, so the next motion command is refused). Each crash is counted
(``CmmMachine.collisions``) and logged as ``cmm_sim.collision``. Durations (travel, the probing stroke at its own
speed, a fixed overhead per touch, homing) are real-time figures multiplied by ``time_scale`` (0 = instant).
``CmmSession`` is one connection's protocol state, transport-free: it answers command lines through a ``send``
callable.
"""

from __future__ import annotations

import threading
from collections.abc import Callable

import numpy as np
import structlog
from scipy.spatial.transform import Rotation, Slerp

from hilcal.protocols.cmm import (
    COORDINATE_DECIMALS,
    DEFAULT_SEARCH_DISTANCE_MM,
    ENCODING,
    ERRORS,
    LATCHING_ERRORS,
    MACHINE_VOLUME_LIMIT_MM,
    MAX_SEARCH_DISTANCE_MM,
    MOTION_COMMANDS,
    PRINTABLE_MAX,
    PRINTABLE_MIN,
    SEARCH_PROPERTY,
    SESSION_FREE_COMMANDS,
    TERMINATOR,
    Command,
    ErrorCode,
    Marker,
)
from hilcal.robot import Robot
from sim_devices.cmm.commands import Call, CommandRejected, axes_by_name, parse_command_line
from sim_devices.cmm.config import CmmServerConfig
from sim_devices.cmm.faults import FaultInjector, FaultPlan
from sim_devices.rig.rig import SimulatedRig

log = structlog.get_logger(__name__)

PENETRATION_TOL_MM = 1e-6
"""A move enters a sphere when it comes closer to its centre than the radius less this (a probe stopped on a
surface may leave it, or move along it)."""
WAY_STEP_DEG = 0.5
"""The platform's way between two looks is sampled every this much turn (a sphere 1 m out then strays at most 10 µm
from the straight steps between the samples)."""
MAX_WAY_STEPS = 512


class MotionAborted(Exception):
    """A motion that failed after its acknowledgement, after ``duration_s`` of machine time."""

    def __init__(self, code: ErrorCode, detail: str = "", duration_s: float = 0.0) -> None:
        super().__init__(code.name)
        self.code = code
        self.detail = detail
        self.duration_s = duration_s


def sphere_name(index: int) -> str:
    """How the log names sphere ``index`` of ``CmmMachine.sphere_centres_mm`` (platform spheres first)."""
    return f"platform sphere {index + 1}" if index < 3 else f"base sphere {index - 2}"


class CmmMachine:
    """Axes, homing, error state and the touch physics; shared by all connections."""

    def __init__(self, robot: Robot, rig: SimulatedRig, config: CmmServerConfig) -> None:
        self.robot = robot
        self.rig = rig
        self.config = config
        self.lock = threading.Lock()
        self.homed = False
        self.position_mm = np.zeros(3)
        self.latched: ErrorCode | None = None
        self.latched_detail = ""
        """What latched the error state when no command did (a platform that struck the probe), for the refusals."""
        self.collisions = 0
        """Crashes so far: GoTo or PtMeas approaches into a sphere, illegal touches and platform spheres that struck the
        probe (each logged)."""
        self.machine_time_s = 0.0
        """Every command's duration so far, before ``time_scale``."""
        self._rng = np.random.default_rng([config.seed, 0xC33])
        self._centres: tuple[bytes, np.ndarray, np.ndarray] | None = None
        """The platform pose the machine last saw (as bytes), the sphere centres for it, and the pose."""

    def sphere_centres_mm(self) -> np.ndarray:
        """(6, 3) true sphere centres in the CMM frame: platform spheres first, then base spheres.

        Computed again only when the platform's pose changed (every command and touch asks; the platform rarely
        moves). Then, with the probe homed, whether a platform sphere struck it on its way (``_check_strikes``).
        """
        pose = self.rig.true_pose()
        key = pose.tobytes()
        if self._centres is None or self._centres[0] != key:
            rot = Rotation.from_euler("ZYX", pose[[5, 4, 3]], degrees=True)
            platform_base = rot.apply(self.robot.platform_spheres) + pose[:3]
            previous = self._centres
            self._centres = (key, self.rig.to_cmm(np.vstack([platform_base, self.robot.base_spheres])), pose)
            if previous is not None and self.homed:
                self._check_strikes(self._platform_way(previous[2], pose))
        return self._centres[1].copy()

    def _platform_way(self, pose0: np.ndarray, pose1: np.ndarray) -> np.ndarray:
        """(n + 1, 3, 3) platform sphere centres (CMM frame) on the platform's way from pose0 to pose1: the poses
        between interpolated (translation straight, orientation by slerp), a sample every ``WAY_STEP_DEG`` of turn.

        The machine sees only the poses at its commands; between them the platform may have moved a long way. This
        way is exact for a move in a straight line at a steady turn, and near any move between two nearby poses.
        """
        rots = Rotation.from_euler("ZYX", np.vstack([pose0, pose1])[:, [5, 4, 3]], degrees=True)
        turn_deg = float(np.degrees((rots[0].inv() * rots[1]).magnitude()))
        n = int(min(MAX_WAY_STEPS, max(1, np.ceil(turn_deg / WAY_STEP_DEG))))
        t = np.linspace(0.0, 1.0, n + 1)
        R = Slerp([0.0, 1.0], rots)(t).as_matrix()
        shift = pose0[:3] + t[:, None] * (pose1[:3] - pose0[:3])
        points = np.einsum("nij,kj->nki", R, self.robot.platform_spheres) + shift[:, None, :]
        return self.rig.to_cmm(points.reshape(-1, 3)).reshape(points.shape)

    def _check_strikes(self, way: np.ndarray) -> None:
        """The platform carried its spheres along ``way`` (``_platform_way``) since the machine last looked.

        A sphere that came closer to the probe than its radius on one of the straight steps between the samples
        struck the probe: ``_strike``. A probe already inside a sphere's old place is not struck again.
        """
        r = self.robot.sphere_radius_mm
        for index in range(way.shape[1]):
            a, b = way[:-1, index], way[1:, index]
            p = self.position_mm
            if np.linalg.norm(p - a[0]) < r - PENETRATION_TOL_MM:
                continue
            d = b - a
            t = np.clip(np.sum((p - a) * d, axis=1) / np.maximum(np.sum(d * d, axis=1), 1e-300), 0.0, 1.0)
            if np.min(np.linalg.norm(a + t[:, None] * d - p, axis=1)) < r - PENETRATION_TOL_MM:
                self._strike(index, a[0], b[-1])

    def _strike(self, index: int, c0: np.ndarray, c1: np.ndarray) -> None:
        """Platform sphere ``index``, moving from centre c0 to c1, struck the probe: count and log it, and with
        ``on_collision = "stop"`` latch 2504. A probe the sphere now covers is left on its surface (pushed aside)."""
        p = self.position_mm.copy()
        stop = self.config.on_collision == "stop"
        self.collisions += 1
        log.warning("cmm_sim.collision", kind="struck", command=None, code=int(ErrorCode.COLLISION), stopped=stop,
                    sphere=index, sphere_name=sphere_name(index), from_mm=np.round(c0, 4).tolist(),
                    to_mm=np.round(c1, 4).tolist(), contact_mm=np.round(p, 4).tolist(), collisions=self.collisions)
        r = self.robot.sphere_radius_mm
        gap = p - c1
        dist = float(np.linalg.norm(gap))
        if dist < r:
            away = gap / dist if dist > 0 else (c0 - c1) / np.linalg.norm(c0 - c1)
            self.position_mm = c1 + r * away
        if stop:
            where = ", ".join(f"{v:.3f}" for v in p)
            self.latch(ErrorCode.COLLISION, f"the platform moved {sphere_name(index)} into the probe at ({where})")

    def latch(self, code: ErrorCode | None, detail: str = "") -> None:
        """Enter the error state with ``code`` (None: leave it); ``detail`` goes into the refusals that follow."""
        self.latched, self.latched_detail = code, detail if code is not None else ""

    def refuse_if_struck(self) -> None:
        """Look at the platform now; MotionAborted if it struck the probe since this command was accepted."""
        self.sphere_centres_mm()
        if self.latched is not None:
            raise MotionAborted(self.latched, self.latched_detail)

    def _travel_s(self, to_mm: np.ndarray) -> float:
        return float(np.linalg.norm(to_mm - self.position_mm)) / self.config.travel_speed_mm_s

    def first_contact(self, start: np.ndarray, end: np.ndarray) -> tuple[int, np.ndarray] | None:
        """The first sphere the straight move from start to end enters (index, the point where the probe meets its
        surface), or None when the move stays clear. A start already inside a sphere meets it at once."""
        centres = self.sphere_centres_mm()
        r = self.robot.sphere_radius_mm
        d = end - start
        m = start - centres
        a = float(d @ d)
        if a == 0.0:
            closest = np.linalg.norm(m, axis=1)
            entry = np.zeros(len(centres))
        else:
            b = m @ d
            closest = np.linalg.norm(m + np.clip(-b / a, 0.0, 1.0)[:, None] * d, axis=1)
            c = np.sum(m * m, axis=1) - r * r
            with np.errstate(invalid="ignore"):
                entry = np.maximum((-b - np.sqrt(np.maximum(b * b - a * c, 0.0))) / a, 0.0)
        hit = closest < r - PENETRATION_TOL_MM
        if not hit.any():
            return None
        index = int(np.argmin(np.where(hit, entry, np.inf)))
        return index, start + min(float(entry[index]), 1.0) * d

    def _collision(self, code: ErrorCode, kind: str, command: str, end: np.ndarray, contact: tuple[int, np.ndarray],
                   stop: bool, extra_s: float = 0.0) -> MotionAborted:
        """Count and log a crash; with ``stop`` the probe stops where it met the sphere. The error to raise."""
        index, point = contact
        start = self.position_mm.copy()
        duration = self._travel_s(point) + extra_s
        if stop:
            self.position_mm = point
        self.collisions += 1
        log.warning("cmm_sim.collision", kind=kind, command=command, code=int(code), stopped=stop, sphere=index,
                    sphere_name=sphere_name(index), from_mm=np.round(start, 4).tolist(),
                    to_mm=np.round(end, 4).tolist(), contact_mm=np.round(point, 4).tolist(), collisions=self.collisions)
        what = {"goto": "GoTo path enters", "approach": "PtMeas approach enters",
                "illegal_touch": "PtMeas start point inside a sphere; the approach meets"}[kind]
        depth = self.robot.sphere_radius_mm - np.linalg.norm(start - self.sphere_centres_mm()[index])
        where = "with the probe already inside it" if depth > PENETRATION_TOL_MM else \
            f"at ({', '.join(f'{v:.3f}' for v in point)})"
        return MotionAborted(code, f"{what} {sphere_name(index)} {where}", duration)

    def _inside(self, point: np.ndarray) -> bool:
        r = self.robot.sphere_radius_mm
        return bool(np.any(np.linalg.norm(point - self.sphere_centres_mm(), axis=1) < r - PENETRATION_TOL_MM))

    def home(self) -> float:
        self.homed = True
        self.position_mm = np.zeros(3)
        return self.config.home_time_s

    def goto(self, target: np.ndarray) -> float:
        """Move to target; a path into a sphere is a collision (with ``on_collision = "count"`` only a target
        inside one stops the machine, a path through one is counted and logged)."""
        self.refuse_if_struck()
        contact = self.first_contact(self.position_mm, target)
        if contact is not None:
            stop = self.config.on_collision == "stop" or self._inside(target)
            crash = self._collision(ErrorCode.COLLISION, "goto", "GoTo", target, contact, stop)
            if stop:
                raise crash
        duration = self._travel_s(target)
        self.position_mm = target
        return duration

    def touch(self, target: np.ndarray, ijk: np.ndarray, search_mm: float, plan: FaultPlan) -> tuple[np.ndarray, float]:
        """The touched point (noisy) and the duration; MotionAborted on a miss, a start inside a sphere or an
        approach through one (counted and passed through with ``on_collision = "count"``).

        Duration: the positioning travel to the start, the probed distance (to the touch, or the whole stroke on a
        miss) at ``probing_speed_mm_s`` and ``probe_time_s``. The probe ends back at the start point.
        """
        norm = float(np.linalg.norm(ijk))
        if norm == 0:
            raise MotionAborted(ErrorCode.VECTOR_HAS_NO_NORM)
        self.refuse_if_struck()
        n = ijk / norm
        start = target + search_mm * n
        contact = self.first_contact(self.position_mm, start)
        if self._inside(start):
            assert contact is not None
            raise self._collision(ErrorCode.ILLEGAL_TOUCH, "illegal_touch", "PtMeas", start, contact, True,
                                  self.config.probe_time_s)
        if contact is not None:
            crash = self._collision(ErrorCode.COLLISION, "approach", "PtMeas", start, contact,
                                    self.config.on_collision == "stop", self.config.probe_time_s)
            if self.config.on_collision == "stop":
                raise crash
        centres = self.sphere_centres_mm()
        r = self.robot.sphere_radius_mm
        m = start - centres
        travel_s = self._travel_s(start) + self.config.probe_time_s
        self.position_mm = start
        b = m @ -n
        c = np.sum(m * m, axis=1) - r * r
        disc = b * b - c
        with np.errstate(invalid="ignore"):
            s = np.where(disc >= 0, -b - np.sqrt(np.maximum(disc, 0.0)), np.inf)
        s = np.where((s >= 0) & (s <= 2.0 * search_mm), s, np.inf)
        if plan.miss or not np.isfinite(s.min()):
            raise MotionAborted(ErrorCode.SURFACE_NOT_FOUND, "injected miss" if plan.miss else "",
                                travel_s + 2.0 * search_mm / self.config.probing_speed_mm_s)
        point = start - s.min() * n + self._rng.normal(0.0, self.config.noise_sigma_mm, 3)
        if plan.outlier:
            point = point + self.config.outlier_mm * n
        return point, travel_s + float(s.min()) / self.config.probing_speed_mm_s


def _fmt(value: float) -> str:
    return f"{value:.{COORDINATE_DECIMALS}f}"


def _error_body(code: ErrorCode, method: str, detail: str) -> str:
    spec = ERRORS[code]
    text = spec.text + (f": {detail}" if detail else "")
    safe = "".join(ch if PRINTABLE_MIN <= ord(ch) <= PRINTABLE_MAX and ch != '"' else "'" for ch in text)
    safe_method = "".join(ch for ch in method if ch.isalnum() or ch == ".")
    return f'{Marker.ERROR} Error({int(spec.severity)}, {int(code):04d}, "{safe_method}", "{safe}")'


class CmmSession:
    """One connection's protocol state; turns command lines into response bytes through ``send``."""

    def __init__(
        self,
        machine: CmmMachine,
        faults: FaultInjector,
        send: Callable[[bytes], None],
        wait: Callable[[float], bool],
    ) -> None:
        self.machine = machine
        self.faults = faults
        self.send = send
        self.wait = wait  # sleeps for a duration; True if the server is stopping
        self.in_session = False
        self.search_mm = DEFAULT_SEARCH_DISTANCE_MM

    def handle_line(self, raw: bytes) -> None:
        """Answer one command line (terminator removed)."""
        try:
            cmd = parse_command_line(raw)
        except CommandRejected as rej:
            log.info("cmm_sim.rejected", code=int(rej.code), detail=rej.detail, raw=raw[:200])
            self._emit(rej.tag, [], _error_body(rej.code, rej.method, rej.detail), FaultPlan())
            return
        try:
            action = self._check(cmd.call)
        except CommandRejected as rej:
            log.info("cmm_sim.rejected", tag=cmd.tag, code=int(rej.code), detail=rej.detail)
            self._emit(cmd.tag, [], _error_body(rej.code, cmd.call.name, rej.detail), FaultPlan())
            return
        plan = self.faults.draw(cmd.call.name)
        if plan.silence:
            log.info("cmm_sim.fault_silence", tag=cmd.tag, command=cmd.call.name)
            return
        ack = f"{cmd.tag} {Marker.ACK}".encode(ENCODING) + TERMINATOR
        data: list[str] = []
        try:
            with self.machine.lock:
                duration, data = action(plan)
        except MotionAborted as abort:
            with self.machine.lock:
                if abort.code in LATCHING_ERRORS and self.machine.latched is None:  # else struck meanwhile
                    self.machine.latch(abort.code)
            final, duration = _error_body(abort.code, cmd.call.name, abort.detail), abort.duration_s
        else:
            final = str(Marker.DONE)
        with self.machine.lock:
            self.machine.machine_time_s += duration
        delay_s = duration * self.machine.config.time_scale
        if delay_s > 0:
            self.send(ack)
            ack = b""
            if self.wait(delay_s):
                return
        self._emit(cmd.tag, data, final, plan, ack)

    def _emit(self, tag: str, data: list[str], final: str, plan: FaultPlan, lead: bytes = b"") -> None:
        """Data lines then the final line, with the planned garbage and cut applied, in one write after `lead`.

        With no machine time to wait (time_scale 0 or an instant command) `lead` is the acknowledgement: a CMM
        that finishes at once sends all its lines together.
        """
        lines = [f"{tag} {Marker.DATA} {d}" for d in data] + [f"{tag} {final}"]
        if plan.partial:
            cut = lines[0].encode(ENCODING)
            log.info("cmm_sim.fault_partial", tag=tag, sent=cut[: len(cut) // 2])
            self.send(lead + cut[: len(cut) // 2])
            return
        out = [lead]
        for i, line in enumerate(lines):
            if plan.garbage and i == len(lines) - 1:
                out += [self.faults.garbage_line() for _ in range(self.machine.config.garbage_lines)]
            out.append(line.encode(ENCODING) + TERMINATOR)
        self.send(b"".join(out))

    def _check(self, call: Call) -> Callable[[FaultPlan], tuple[float, list[str]]]:
        """Validate a command in the current state; the action to run after the acknowledgement."""
        try:
            name = Command(call.name)
        except ValueError:
            raise CommandRejected("", ErrorCode.UNSUPPORTED_COMMAND, call.name[:40]) from None
        if not self.in_session and name not in SESSION_FREE_COMMANDS:
            raise CommandRejected("", ErrorCode.BAD_CONTEXT, "no session (StartSession first)")
        m = self.machine
        with m.lock:
            m.sphere_centres_mm()  # the platform may have moved since the last command (and struck the probe)
        try:
            if name in (Command.START_SESSION, Command.END_SESSION, Command.HOME, Command.CLEAR_ALL_ERRORS):
                if call.args:
                    raise ValueError(f"{name} takes no arguments")
            if name in MOTION_COMMANDS:
                with m.lock:
                    latched, detail, homed = m.latched, m.latched_detail, m.homed
                if latched is not None:
                    raise CommandRejected("", ErrorCode.TRANSACTION_ABORTED,
                                          f"after error {int(latched):04d}" + (f": {detail}" if detail else ""))
                if name is not Command.HOME and not homed:
                    raise CommandRejected("", ErrorCode.BAD_CONTEXT, "machine not homed (Home first)")
            match name:
                case Command.START_SESSION:
                    return self._start_session
                case Command.END_SESSION:
                    return self._end_session
                case Command.HOME:
                    return lambda _plan: (m.home(), [])
                case Command.CLEAR_ALL_ERRORS:
                    return self._clear
                case Command.GET_ERROR_INFO:
                    return self._error_info(call)
                case Command.SET_PROP:
                    return self._set_prop(call)
                case Command.GO_TO:
                    axes = axes_by_name(call, ("X", "Y", "Z"), ())
                    if not axes:
                        raise ValueError("GoTo needs at least one of X, Y, Z")
                    target = self._target(axes)
                    return lambda _plan: (m.goto(target), [])
                case Command.PT_MEAS:
                    axes = axes_by_name(call, ("X", "Y", "Z", "IJK"), ("X", "Y", "Z", "IJK"))
                    target = self._target(axes)
                    ijk = np.array(axes["IJK"])
                    search = self.search_mm

                    def ptmeas(plan: FaultPlan) -> tuple[float, list[str]]:
                        point, duration = m.touch(target, ijk, search, plan)
                        return duration, [f"X({_fmt(point[0])}), Y({_fmt(point[1])}), Z({_fmt(point[2])})"]

                    return ptmeas
        except ValueError as err:
            raise CommandRejected("", ErrorCode.INCORRECT_ARGUMENTS, str(err)[:80]) from None
        raise CommandRejected("", ErrorCode.UNSUPPORTED_COMMAND, call.name)

    def _target(self, axes: dict[str, tuple[float, ...]]) -> np.ndarray:
        with self.machine.lock:
            target = self.machine.position_mm.copy()
        for i, axis in enumerate(("X", "Y", "Z")):
            if axis in axes:
                target[i] = axes[axis][0]
        if np.any(np.abs(target) > MACHINE_VOLUME_LIMIT_MM):
            raise CommandRejected("", ErrorCode.OUT_OF_MACHINE_VOLUME)
        return target

    def _start_session(self, _plan: FaultPlan) -> tuple[float, list[str]]:
        self.in_session = True
        self.search_mm = DEFAULT_SEARCH_DISTANCE_MM
        self.machine.latch(None)
        return 0.0, []

    def _end_session(self, _plan: FaultPlan) -> tuple[float, list[str]]:
        self.in_session = False
        return 0.0, []

    def _clear(self, _plan: FaultPlan) -> tuple[float, list[str]]:
        self.machine.latch(None)
        return 0.0, []

    def _error_info(self, call: Call) -> Callable[[FaultPlan], tuple[float, list[str]]]:
        if len(call.args) != 1 or not isinstance(call.args[0], float) or call.args[0] != int(call.args[0]):
            raise ValueError("GetErrorInfo needs one integer code")
        try:
            code = ErrorCode(int(call.args[0]))
        except ValueError:
            raise CommandRejected("", ErrorCode.ARGUMENT_OUT_OF_RANGE, "unknown error code") from None
        return lambda _plan: (0.0, [f'ErrorInfo({int(code):04d}, "{ERRORS[code].text}")'])

    def _set_prop(self, call: Call) -> Callable[[FaultPlan], tuple[float, list[str]]]:
        if len(call.args) != 1 or not isinstance(call.args[0], Call):
            raise ValueError("SetProp needs one property")
        prop = call.args[0]
        if prop.name != SEARCH_PROPERTY:
            raise CommandRejected("", ErrorCode.BAD_PROPERTY, prop.name[:60])
        if len(prop.args) != 1 or not isinstance(prop.args[0], float):
            raise ValueError(f"{SEARCH_PROPERTY} needs one number")
        value = prop.args[0]
        if not 0 < value <= MAX_SEARCH_DISTANCE_MM:
            raise CommandRejected(
                "", ErrorCode.ARGUMENT_OUT_OF_RANGE, f"search distance must be in (0, {MAX_SEARCH_DISTANCE_MM}]"
            )

        def apply(_plan: FaultPlan) -> tuple[float, list[str]]:
            self.search_mm = value
            return 0.0, []

        return apply
