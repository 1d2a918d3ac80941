"""The simulated CMM's machine and protocol session: touch physics, homing, error state, command responses.

Physics: the six tooling spheres of the SimulatedRig (platform spheres moving with ``rig.true_pose()``, base
spheres fixed) expressed in the CMM frame with ``rig.to_cmm``. ``PtMeas(X,Y,Z,IJK)`` moves the probe from
target + s*IJK along -IJK for up to 2*s (s = search distance) and returns the first surface touched plus
Gaussian noise; no surface on that path is error 1006 "Surface not found". Durations are real-time
figures multiplied by ``time_scale`` (0 = instant). ``CmmSession`` is one connection's protocol state,
transport-free: it answers command lines through a ``send`` callable.
"""

from __future__ import annotations

import threading
from collections.abc import Callable

import numpy as np
import structlog
from scipy.spatial.transform import Rotation

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


class MotionAborted(Exception):
    """A motion that failed after its acknowledgement."""

    def __init__(self, code: ErrorCode, detail: str = "") -> None:
        super().__init__(code.name)
        self.code = code
        self.detail = detail


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
        self._rng = np.random.default_rng([config.seed, 0xC33])
        self._centres: tuple[bytes, np.ndarray] | None = None

    def sphere_centres_mm(self) -> np.ndarray:
        """(6, 3) true sphere centres in the CMM frame: platform spheres first, then base spheres.

        Computed again only when the platform's pose changed (every touch asks; the platform rarely moves).
        """
        pose = self.rig.true_pose()
        key = pose.tobytes()
        if self._centres is None or self._centres[0] != key:
            rot = Rotation.from_euler("ZYX", pose[[5, 4, 3]], degrees=True)
            platform_base = rot.apply(self.robot.platform_spheres) + pose[:3]
            self._centres = (key, self.rig.to_cmm(np.vstack([platform_base, self.robot.base_spheres])))
        return self._centres[1].copy()

    def _travel_s(self, to_mm: np.ndarray) -> float:
        return float(np.linalg.norm(to_mm - self.position_mm)) / self.config.travel_speed_mm_s

    def home(self) -> float:
        self.homed = True
        self.position_mm = np.zeros(3)
        return self.config.home_time_s

    def goto(self, target: np.ndarray) -> float:
        r = self.robot.sphere_radius_mm
        if np.any(np.linalg.norm(self.sphere_centres_mm() - target, axis=1) < r):
            raise MotionAborted(ErrorCode.COLLISION, "GoTo target inside a sphere")
        duration = self._travel_s(target)
        self.position_mm = target
        return duration

    def touch(self, target: np.ndarray, ijk: np.ndarray, search_mm: float, plan: FaultPlan) -> tuple[np.ndarray, float]:
        """The touched point (noisy) and the duration; MotionAborted on a miss or a start inside a sphere."""
        norm = float(np.linalg.norm(ijk))
        if norm == 0:
            raise MotionAborted(ErrorCode.VECTOR_HAS_NO_NORM)
        n = ijk / norm
        start = target + search_mm * n
        duration = self._travel_s(start) + self.config.probe_time_s
        self.position_mm = start
        centres = self.sphere_centres_mm()
        r = self.robot.sphere_radius_mm
        m = start - centres
        if np.any(np.linalg.norm(m, axis=1) < r):
            raise MotionAborted(ErrorCode.ILLEGAL_TOUCH, "probe start inside a sphere")
        b = m @ -n
        c = np.sum(m * m, axis=1) - r * r
        disc = b * b - c
        with np.errstate(invalid="ignore"):
            s = np.where(disc >= 0, -b - np.sqrt(np.maximum(disc, 0.0)), np.inf)
        s = np.where((s >= 0) & (s <= 2.0 * search_mm), s, np.inf)
        if plan.miss or not np.isfinite(s.min()):
            raise MotionAborted(ErrorCode.SURFACE_NOT_FOUND, "injected miss" if plan.miss else "")
        point = start - s.min() * n + self._rng.normal(0.0, self.config.noise_sigma_mm, 3)
        if plan.outlier:
            point = point + self.config.outlier_mm * n
        return point, duration


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
                if abort.code in LATCHING_ERRORS:
                    self.machine.latched = abort.code
            final, duration = _error_body(abort.code, cmd.call.name, abort.detail), self.machine.config.probe_time_s
        else:
            final = str(Marker.DONE)
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
        try:
            if name in (Command.START_SESSION, Command.END_SESSION, Command.HOME, Command.CLEAR_ALL_ERRORS):
                if call.args:
                    raise ValueError(f"{name} takes no arguments")
            if name in MOTION_COMMANDS:
                with m.lock:
                    latched, homed = m.latched, m.homed
                if latched is not None:
                    raise CommandRejected("", ErrorCode.TRANSACTION_ABORTED, f"after error {int(latched):04d}")
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
        self.machine.latched = None
        return 0.0, []

    def _end_session(self, _plan: FaultPlan) -> tuple[float, list[str]]:
        self.in_session = False
        return 0.0, []

    def _clear(self, _plan: FaultPlan) -> tuple[float, list[str]]:
        self.machine.latched = None
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
