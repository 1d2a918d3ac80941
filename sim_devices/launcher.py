"""All simulated devices in one process: the servo controller (SLCAN + Modbus TCP) and the CMM (pty + TCP).

``start_sim(config)`` runs them in-process (a context manager); ``run_sim_process`` is ``hilcal sim``: it prints
the channels and serves until SIGINT/SIGTERM; ``spawn_sim_subprocess`` starts ``python -m sim_devices.launcher
--json`` as a separate process and returns its channels (``hilcal run --sim``). Everything binds to 127.0.0.1.

The CMM reads the platform pose through the controller (``SimulatedController.true_pose``, under its lock), so it
never sees a half-updated rig. With a ``state_file`` the controller's parameter banks (live, backup, saved), the
rig's reported leg lengths, motion directions and clock are written atomically (temp file + ``os.replace``) on
every change, before the change is acknowledged on the wire, and loaded at start: a simulator restarted on the
same file finds the controller as it was (powered up DISABLED, like a real controller after a power cycle).

Example configuration (every key optional; relative paths are relative to the file)::

    robot = "robots/plant3.toml"    # default: the built-in paper Table 1 robot
    state_file = "sim_state.json"   # default: no persistence

    [rig]                           # SimulatedRig truth: seed and errors, plus any RigConfig field
    seed = 0
    errors = "table2"               # table2..table5, zero, or an errors TOML file
    leg_resolution_mm = 0.001
    [rig.effects.thermal_expansion]
    enabled = true

    [controller]                    # ControllerSimConfig; time_scale defaults to 100 here
    time_scale = 100.0
    [controller.can_faults]
    drop_rate = 0.001

    [cmm]                           # CmmServerConfig (time_scale defaults to 0.0005, tcp_port to 0 here)
    noise_sigma_mm = 0.002          # probing noise per coordinate
    alignment_error_mm = 2.0        # error of the published T_cmm<-base (a station's rough CMM set-up)
    alignment_error_deg = 0.02
    [cmm.faults]
    garbage = 0.01
"""

from __future__ import annotations

import argparse
import contextlib
import fcntl
import json
import logging
import os
import select
import signal
import subprocess
import sys
import tempfile
import threading
import time
import tomllib
from collections.abc import Sequence
from datetime import UTC, datetime
from pathlib import Path
from types import TracebackType
from typing import IO, Annotated, Any, Literal, cast

import numpy as np
import structlog
from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator
from scipy.spatial.transform import Rotation

from hilcal.protocols.controller_states import Command, ControllerState, FaultCode, RefusalReason
from hilcal.protocols.registers import ParamCommand, ParamStatus
from hilcal.robot import Robot, RobotFileError, load_robot
from sim_devices.cmm_server import CmmServerConfig, CmmServerHandle, start_cmm_server
from sim_devices.config import BUILTIN_ERROR_SETS, GeometryErrors, RigConfig, load_errors
from sim_devices.controller import (
    ControllerServers,
    ControllerSimConfig,
    ControllerSnapshot,
    SimulatedController,
    serve_controller,
)
from sim_devices.rig import SimulatedRig

log = structlog.get_logger(__name__)

HOST = "127.0.0.1"
STATE_FORMAT = "hilcal-sim-state"
STATE_VERSION = 1
MOVING_SAVE_PERIOD_S = 0.2
"""While the legs move, their lengths are saved at most this often (real time); state changes at once."""
CLOCK_STEP_S = 10.0
"""The rig clock follows simulated time in steps of this many simulated seconds."""
DIRECTION_STEP_MM = 0.002
DEFAULT_LOCK_TIMEOUT_S = 5.0
DEFAULT_SPAWN_TIMEOUT_S = 30.0
STOP_POLL_S = 0.1
PROJECT_ROOT = Path(__file__).resolve().parents[1]


class SimConfigError(ValueError):
    """A simulator configuration that cannot be read or is not valid."""


class SimStateError(RuntimeError):
    """The state file cannot be used: unreadable, for another robot, or held by another simulator."""


class SimStartError(RuntimeError):
    """The simulator subprocess did not start (it died or printed no channels in time)."""


# ---------------------------------------------------------------------- configuration


class SimRigSettings(BaseModel):
    """The rig: ``seed``, ``errors`` (built-in name or TOML file) and any further ``RigConfig`` field."""

    model_config = ConfigDict(extra="allow", frozen=True)

    seed: int = 0
    errors: str = Field(default="table2", description=f"one of {', '.join(BUILTIN_ERROR_SETS)} or an errors TOML file")

    @model_validator(mode="after")
    def _valid_rig_fields(self) -> SimRigSettings:
        try:
            RigConfig.model_validate({**(self.model_extra or {}), "seed": self.seed, "errors": GeometryErrors.zero()})
        except ValidationError as err:
            raise ValueError("; ".join(
                f"{'.'.join(str(p) for p in e['loc'])}: {e['msg'].removeprefix('Value error, ')}" for e in err.errors()
            )) from None
        return self

    def rig_config(self, robot: Robot) -> RigConfig:
        """The RigConfig with the errors loaded (ValueError naming the errors source if they cannot be)."""
        errors = load_errors(self.errors, robot)
        return RigConfig.model_validate({**(self.model_extra or {}), "seed": self.seed, "errors": errors})


class SimControllerConfig(ControllerSimConfig):
    """ControllerSimConfig with the launcher's default time scale: servo and rig clock × 100.

    A 56-pose plan (~870 moves of at most 50 mm) then takes ~30 s: each move is bounded by the 20 ms heartbeat,
    and the rig clock covers about the duration of a real run (~50 min).
    """

    time_scale: float = Field(default=100.0, gt=0, description="simulated seconds per real second")


class SimCmmConfig(CmmServerConfig):
    """CmmServerConfig with fast defaults, a TCP endpoint, and the error of the published CMM alignment."""

    time_scale: float = Field(default=0.0005, ge=0, description="multiplies every CMM duration; 0 = instant")
    tcp_port: int | None = Field(default=0, ge=0, le=65535, description="None: pty only; 0: ephemeral port")
    alignment_error_mm: float = Field(default=2.0, ge=0, description="offset of the published T_cmm<-base")
    alignment_error_deg: float = Field(default=0.02, ge=0, description="rotation error of the published T_cmm<-base")

    def server_config(self, default_seed: int) -> CmmServerConfig:
        """The CmmServerConfig to start the server with (seed: the rig seed unless set here)."""
        data = self.model_dump(exclude={"alignment_error_mm", "alignment_error_deg"})
        if "seed" not in self.model_fields_set:
            data["seed"] = default_seed
        return CmmServerConfig.model_validate(data)


class SimConfig(BaseModel):
    """Everything ``hilcal sim`` runs (see the module docstring for a TOML example)."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    robot: Path | None = Field(default=None, description="robot TOML file; None: the built-in paper Table 1 robot")
    rig: SimRigSettings = Field(default_factory=SimRigSettings)
    controller: SimControllerConfig = Field(default_factory=SimControllerConfig)
    cmm: SimCmmConfig = Field(default_factory=SimCmmConfig)
    state_file: Path | None = Field(default=None, description="controller and rig state, kept across restarts")


def _format_errors(err: ValidationError, source: str) -> str:
    lines = [f"{source}: {err.error_count()} problem(s)"]
    for e in err.errors():
        where = ".".join(str(p) for p in e["loc"]) or "<top>"
        lines.append(f"  {where}: {e['msg'].removeprefix('Value error, ')}")
    return "\n".join(lines)


def _resolve(base: Path, value: Any) -> Any:
    """A relative path string resolved against base (other values unchanged)."""
    if isinstance(value, str) and value and not Path(value).is_absolute():
        return str(base / value)
    return value


def load_sim_config(
    path: str | Path | None = None, *, state_file: str | Path | None = None, seed: int | None = None
) -> SimConfig:
    """The configuration from a TOML file (None: defaults), with ``--state-file``/``--seed`` overrides.

    Relative ``robot``, ``state_file`` and errors-file paths are relative to the file. SimConfigError otherwise.
    """
    data: dict[str, Any] = {}
    source = "simulator defaults"
    if path is not None:
        p = Path(path)
        source = f"simulator config {p}"
        try:
            data = tomllib.loads(p.read_text())
        except OSError as err:
            raise SimConfigError(f"{source}: cannot read: {err.strerror}") from None
        except tomllib.TOMLDecodeError as err:
            raise SimConfigError(f"{source}: not valid TOML: {err}") from None
        base = p.resolve().parent
        for key in ("robot", "state_file"):
            data[key] = _resolve(base, data.get(key))
        rig = data.get("rig")
        if isinstance(rig, dict) and isinstance(rig.get("errors"), str) and rig["errors"] not in BUILTIN_ERROR_SETS:
            data["rig"] = {**rig, "errors": _resolve(base, rig["errors"])}
    if state_file is not None:
        data["state_file"] = str(state_file)
    if seed is not None:
        rig = data.get("rig")
        data["rig"] = {**(rig if isinstance(rig, dict) else {}), "seed": seed}
    data = {k: v for k, v in data.items() if v is not None}
    try:
        return SimConfig.model_validate(data)
    except ValidationError as err:
        raise SimConfigError(_format_errors(err, source)) from None


# ---------------------------------------------------------------------- persistent state


Floats42 = Annotated[list[float], Field(min_length=42, max_length=42)]
Floats6 = Annotated[list[float], Field(min_length=6, max_length=6)]


class BankState(BaseModel):
    """The controller's parameter banks (float32 values, stored exactly) and counters."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    live: Floats42
    backup: Floats42 | None
    saved: Floats42
    commit_counter: int
    save_counter: int


class RigState(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)

    reported_lengths_mm: Floats6
    direction: Floats6
    time_s: float = Field(ge=0)


class SimState(BaseModel):
    """The content of a state file."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    format: Literal["hilcal-sim-state"] = STATE_FORMAT
    version: Literal[1] = STATE_VERSION
    robot: str
    written_at: str
    sequence: int
    controller_state: str
    banks: BankState
    rig: RigState


class StateStore:
    """One state file, held exclusively (``<file>.lock``, flock) while a simulator uses it."""

    def __init__(self, path: Path, robot_name: str, lock_timeout_s: float = DEFAULT_LOCK_TIMEOUT_S) -> None:
        self.path = Path(path)
        self.robot_name = robot_name
        self.sequence = 0
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._lock_fd = os.open(self.path.with_name(self.path.name + ".lock"), os.O_RDWR | os.O_CREAT, 0o644)
        deadline = time.monotonic() + lock_timeout_s
        while True:
            try:
                fcntl.flock(self._lock_fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
                break
            except BlockingIOError:
                if time.monotonic() >= deadline:
                    os.close(self._lock_fd)
                    raise SimStateError(
                        f"state file {self.path} is in use by another simulator (lock held for {lock_timeout_s} s)"
                    ) from None
                time.sleep(0.05)

    def load(self) -> SimState | None:
        """The saved state, None if there is no file; SimStateError if it is unreadable or for another robot."""
        try:
            text = self.path.read_text()
        except FileNotFoundError:
            return None
        except OSError as err:
            raise SimStateError(f"state file {self.path}: cannot read: {err.strerror}") from None
        try:
            state = SimState.model_validate_json(text)
        except ValidationError as err:
            raise SimStateError(_format_errors(err, f"state file {self.path}")) from None
        if state.robot != self.robot_name:
            raise SimStateError(
                f"state file {self.path} is for robot {state.robot!r}, the simulator runs {self.robot_name!r}"
            )
        self.sequence = state.sequence
        return state

    def write(self, state: SimState) -> None:
        """Replace the file atomically (temp file, fsync, os.replace)."""
        tmp = self.path.with_name(f".{self.path.name}.{os.getpid()}.tmp")
        with open(tmp, "w") as fh:
            fh.write(state.model_dump_json(indent=1))
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, self.path)

    def close(self) -> None:
        """Release the lock (idempotent); the state file stays."""
        if self._lock_fd >= 0:
            os.close(self._lock_fd)
            self._lock_fd = -1


def _restore_rig(rig: SimulatedRig, state: RigState) -> None:
    """Put the rig at the saved lengths, arriving in the saved direction of each leg, at the saved time."""
    lengths = np.asarray(state.reported_lengths_mm, dtype=float)
    direction = np.sign(np.asarray(state.direction, dtype=float))
    lo, hi = rig.robot.leg_limits
    step = max(DIRECTION_STEP_MM, 2.0 * rig.config.leg_resolution_mm)
    rig.move_to_lengths(np.clip(lengths - direction * step, lo, hi))
    rig.move_to_lengths(lengths)
    rig.set_time(state.time_s)


class PersistentController(SimulatedController):
    """SimulatedController whose rig clock follows simulated time and whose state is saved on every change.

    Every public method that can change the banks, the state or the legs saves (under the model lock, before
    returning, i.e. before the change is acknowledged on CAN or Modbus) when something changed; while the legs
    move (state MOVING, banks unchanged) at most every MOVING_SAVE_PERIOD_S.
    """

    def __init__(
        self,
        robot: Robot,
        rig: SimulatedRig,
        config: ControllerSimConfig,
        store: StateStore | None = None,
        banks: BankState | None = None,
    ) -> None:
        super().__init__(robot, rig, config)
        self._sim_rig = rig
        self._store = store
        self._clock_origin = (time.monotonic(), rig.time_s)
        self._saved_key: tuple[Any, ...] | None = None
        self._saved_motion: tuple[Any, ...] | None = None
        self._saved_at = 0.0
        if banks is not None:
            self.restore_banks(banks.live, banks.saved, banks.backup, banks.commit_counter, banks.save_counter)

    def _tick(self) -> None:
        """Advance the rig clock to the simulated time now (whole CLOCK_STEP_S steps)."""
        real0, sim0 = self._clock_origin
        now = sim0 + (time.monotonic() - real0) * self.config.time_scale
        if now - self._sim_rig.time_s >= CLOCK_STEP_S:
            self._sim_rig.set_time(now)

    def current_state(self) -> SimState:
        """What a state file holds, read now in one piece."""
        with self._lock:
            snap = super().snapshot()
            backup = self.backup_parameters()
            registers = self.param_registers()
            return SimState(
                robot=self.robot.name,
                written_at=datetime.now(UTC).isoformat(timespec="milliseconds"),
                sequence=self._store.sequence + 1 if self._store is not None else 0,
                controller_state=snap.state.name,
                banks=BankState(
                    live=self.live_parameters().tolist(),
                    backup=None if backup is None else backup.tolist(),
                    saved=self.saved_parameters().tolist(),
                    commit_counter=registers["commit_counter"],
                    save_counter=registers["save_counter"],
                ),
                rig=RigState(
                    reported_lengths_mm=self._sim_rig.reported_lengths().tolist(),
                    direction=self._sim_rig.motion_direction().tolist(),
                    time_s=self._sim_rig.time_s,
                ),
            )

    def save_state(self, force: bool = False) -> None:
        """Write the state file if anything but the clock changed (legs while moving: throttled); force: always."""
        if self._store is None:
            return
        with self._lock:
            state = self.current_state()
            key = (state.controller_state, state.banks)
            motion = (state.rig.reported_lengths_mm, state.rig.direction)
            now = time.monotonic()
            if not force:
                if key == self._saved_key and motion == self._saved_motion:
                    return
                moving = state.controller_state == ControllerState.MOVING.name
                same_banks = self._saved_key is not None and state.banks == self._saved_key[1]
                if moving and same_banks and now - self._saved_at < MOVING_SAVE_PERIOD_S:
                    return
            self._store.write(state)
            self._store.sequence = state.sequence
            self._saved_key, self._saved_motion, self._saved_at = key, motion, now

    def snapshot(self) -> ControllerSnapshot:
        with self._lock:
            self._tick()
            snap = super().snapshot()
            self.save_state()
            return snap

    def command(self, command: Command) -> RefusalReason:
        with self._lock:
            reason = super().command(command)
            self.save_state()
            return reason

    def set_setpoint(self, lengths_mm: Sequence[float], tag: int = 0) -> RefusalReason:
        with self._lock:
            reason = super().set_setpoint(lengths_mm, tag)
            self.save_state()
            return reason

    def param_command(self, command: ParamCommand) -> ParamStatus:
        with self._lock:
            status = super().param_command(command)
            self.save_state()
            return status

    def install_parameters(self, values: Sequence[float]) -> None:
        with self._lock:
            super().install_parameters(values)
            self.save_state()

    def inject_fault(self, code: FaultCode = FaultCode.DRIVE) -> None:
        with self._lock:
            super().inject_fault(code)
            self.save_state()

    def press_estop(self, source: Literal["input", "request"] = "input") -> None:
        with self._lock:
            super().press_estop(source)
            self.save_state()

    def true_pose(self) -> np.ndarray:
        with self._lock:
            self._tick()
            return super().true_pose()


class LockedRigView:
    """The rig as the CMM sees it: the pose is read through the controller, under its lock."""

    def __init__(self, rig: SimulatedRig, controller: SimulatedController) -> None:
        self._rig = rig
        self._controller = controller

    def true_pose(self) -> np.ndarray:
        return self._controller.true_pose()

    def to_cmm(self, points_base_mm: np.ndarray) -> np.ndarray:
        return self._rig.to_cmm(points_base_mm)


# ---------------------------------------------------------------------- in-process simulator


def published_alignment(rig: SimulatedRig, error_mm: float, error_deg: float, seed: int) -> np.ndarray:
    """T_cmm<-base (4x4) of the rig's CMM placement, spoiled by error_mm and error_deg (seeded, in the base frame)."""
    origin = rig.to_cmm(np.zeros(3))
    T = np.eye(4)
    T[:3, :3] = (rig.to_cmm(np.eye(3)) - origin).T
    T[:3, 3] = origin
    rng = np.random.default_rng([seed, 0xA11])
    axis, shift = rng.normal(size=3), rng.normal(size=3)
    spoil = np.eye(4)
    spoil[:3, :3] = Rotation.from_rotvec(np.radians(error_deg) * axis / np.linalg.norm(axis)).as_matrix()
    spoil[:3, 3] = error_mm * shift / np.linalg.norm(shift)
    return T @ spoil


class SimHandle:
    """The running simulator: ``controller``, ``controller_servers``, ``cmm_server``, ``rig``, ``alignment``."""

    def __init__(
        self,
        config: SimConfig,
        robot: Robot,
        rig: SimulatedRig,
        controller: PersistentController,
        controller_servers: ControllerServers,
        cmm_server: CmmServerHandle,
        store: StateStore | None,
        restored: bool = False,
    ) -> None:
        self.config = config
        self.robot = robot
        self.rig = rig
        self.controller = controller
        self.controller_servers = controller_servers
        self.cmm_server = cmm_server
        self.store = store
        self.restored = restored
        """True when the controller and rig state came from an existing state file."""
        cmm = config.cmm
        self.alignment = published_alignment(rig, cmm.alignment_error_mm, cmm.alignment_error_deg, config.rig.seed)
        self._closed = False

    def channels(self) -> dict[str, Any]:
        """Where to connect the real drivers (JSON-serialisable)."""
        servers, cmm = self.controller_servers, self.cmm_server
        out: dict[str, Any] = {
            "can": {"interface": "slcan", "channel": servers.slcan_path, "sleep_after_open": 0},
            "modbus": {"host": HOST, "port": servers.modbus_port, "device_id": self.config.controller.device_id},
            "cmm": {"url": cmm.path or cmm.socket_url, "socket_url": cmm.socket_url},
            "cmm_alignment": self.alignment.tolist(),
            "robot": self.robot.name,
            "robot_path": None if self.config.robot is None else str(self.config.robot),
            "state_file": None if self.store is None else str(self.store.path),
            "pid": os.getpid(),
        }
        if servers.modbus_rtu_path is not None:
            out["modbus_rtu"] = {"serial_port": servers.modbus_rtu_path, "baudrate": 115200,
                                 "device_id": self.config.controller.device_id}
        return out

    def close(self) -> None:
        """Stop the CMM and the controller servers, save the final state, release the state file (idempotent)."""
        if self._closed:
            return
        self._closed = True
        try:
            self.cmm_server.close()
            self.controller_servers.close()
            self.controller.save_state(force=True)
        finally:
            if self.store is not None:
                self.store.close()
        log.info("sim_stopped")

    def __enter__(self) -> SimHandle:
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.close()


def start_sim(config: SimConfig | None = None, *, lock_timeout_s: float = DEFAULT_LOCK_TIMEOUT_S) -> SimHandle:
    """Start the simulated controller and CMM in this process; ``close()`` (or ``with``) stops them.

    Raises RobotFileError / ValueError (bad robot or errors), SimStateError (state file), OSError (transports).
    """
    cfg = config or SimConfig()
    t0 = time.perf_counter()
    robot = load_robot(cfg.robot)
    rig = SimulatedRig(robot, cfg.rig.rig_config(robot))
    store = StateStore(cfg.state_file, robot.name, lock_timeout_s) if cfg.state_file is not None else None
    servers: ControllerServers | None = None
    try:
        saved = store.load() if store is not None else None
        if saved is not None:
            _restore_rig(rig, saved.rig)
        controller = PersistentController(robot, rig, cfg.controller, store, saved.banks if saved else None)
        controller.save_state(force=True)
        servers = serve_controller(controller)
        cmm = start_cmm_server(robot, cast(SimulatedRig, LockedRigView(rig, controller)),
                               cfg.cmm.server_config(cfg.rig.seed))
    except BaseException:
        if servers is not None:
            servers.close()
        if store is not None:
            store.close()
        raise
    handle = SimHandle(cfg, robot, rig, controller, servers, cmm, store, restored=saved is not None)
    log.info("sim_started", robot=robot.name, restored=handle.restored, start_s=round(time.perf_counter() - t0, 3),
             can=servers.slcan_path, modbus_port=servers.modbus_port, cmm=cmm.path, cmm_socket=cmm.socket_url)
    return handle


# ---------------------------------------------------------------------- process entry points


def _describe(channels: dict[str, Any], handle: SimHandle) -> str:
    T = np.asarray(channels["cmm_alignment"])
    rows = "\n".join("    [" + ", ".join(f"{v:12.4f}" for v in row) + "]" for row in T)
    cmm, rig = channels["cmm"], handle.config.rig
    lines = [
        f"hilcal simulator: robot {channels['robot']}, errors {rig.errors}, seed {rig.seed}",
        f"  CAN (SLCAN)   {channels['can']['channel']}   "
        f"(can.Bus(interface='slcan', channel='{channels['can']['channel']}', sleep_after_open=0))",
        f"  Modbus TCP    {channels['modbus']['host']}:{channels['modbus']['port']} "
        f"(device id {channels['modbus']['device_id']})",
        f"  CMM           {cmm['url']}" + (f"   or {cmm['socket_url']}" if cmm["socket_url"] else ""),
        "  CMM alignment T_cmm<-base (approximate, as a station's CMM set-up gives it):",
        rows,
    ]
    if channels["state_file"]:
        restored = "restored" if handle.restored else "new"
        lines.append(f"  state file    {channels['state_file']} ({restored})")
    lines.append("Ctrl-C (SIGINT) or SIGTERM stops the simulator.")
    return "\n".join(lines)


def run_sim_process(config: SimConfig, as_json: bool, *, stdin_watch: bool = False) -> int:
    """``hilcal sim``: start everything, print the channels (text or one JSON line), serve until SIGINT/SIGTERM.

    With ``stdin_watch`` it also stops when stdin reaches end of file (the spawning process has gone).
    Returns the exit code: 0 after a clean stop, 2 if the simulator could not start.
    """
    stop = threading.Event()

    def on_signal(signum: int, _frame: object) -> None:
        log.info("sim_signal", signal=signal.Signals(signum).name)
        stop.set()

    previous = {sig: signal.signal(sig, on_signal) for sig in (signal.SIGINT, signal.SIGTERM)}
    try:
        try:
            handle = start_sim(config)
        except (RobotFileError, SimStateError, ValueError, OSError) as err:
            print(f"error: the simulator did not start: {err}", file=sys.stderr, flush=True)
            return 2
        with handle:
            channels = handle.channels()
            print(json.dumps(channels) if as_json else _describe(channels, handle), flush=True)
            watch_fd = sys.stdin.fileno() if stdin_watch else None
            while not stop.is_set():
                if watch_fd is None:
                    stop.wait(STOP_POLL_S)
                    continue
                readable, _, _ = select.select([watch_fd], [], [], STOP_POLL_S)
                if readable and not os.read(watch_fd, 4096):
                    log.info("sim_parent_gone")
                    stop.set()
        return 0
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)


def _configure_logging(verbose: bool) -> None:
    structlog.configure(
        wrapper_class=structlog.make_filtering_bound_logger(logging.INFO if verbose else logging.WARNING),
        logger_factory=lambda *_: structlog.PrintLogger(sys.stderr),
    )


def main(argv: Sequence[str] | None = None) -> int:
    """``python -m sim_devices.launcher [--config FILE] [--json] [--state-file PATH] [--seed N]``."""
    parser = argparse.ArgumentParser(prog="python -m sim_devices.launcher", description=__doc__.split("\n")[0])
    parser.add_argument("--config", type=Path, help="simulator TOML file (default: built-in settings)")
    parser.add_argument("--json", action="store_true", help="print the channels as one JSON line")
    parser.add_argument("--state-file", type=Path, help="keep the controller and rig state in this file")
    parser.add_argument("--seed", type=int, help="rig seed (overrides the file)")
    parser.add_argument("--stdin-watch", action="store_true", help="stop when stdin closes (spawning process gone)")
    parser.add_argument("--verbose", "-v", action="store_true", help="structured logs on stderr")
    args = parser.parse_args(argv)
    _configure_logging(args.verbose)
    try:
        config = load_sim_config(args.config, state_file=args.state_file, seed=args.seed)
    except SimConfigError as err:
        print(f"error: {err}", file=sys.stderr, flush=True)
        return 2
    return run_sim_process(config, args.json, stdin_watch=args.stdin_watch)


def _read_first_line(proc: subprocess.Popen[bytes], deadline: float) -> bytes | None:
    """The first stdout line of proc (without the newline), None if it exits or the deadline passes first."""
    assert proc.stdout is not None
    fd = proc.stdout.fileno()
    buf = b""
    while b"\n" not in buf:
        remaining = deadline - time.monotonic()
        if remaining <= 0:
            return None
        readable, _, _ = select.select([fd], [], [], min(remaining, STOP_POLL_S))
        if readable:
            chunk = os.read(fd, 65536)
            if not chunk:
                return None
            buf += chunk
    return buf.split(b"\n", 1)[0]


def _tail(fh: IO[bytes], limit: int = 4000) -> str:
    fh.flush()
    fh.seek(0)
    text = fh.read().decode(errors="replace").strip()
    return text[-limit:] or "(no output on stderr)"


def spawn_sim_subprocess(
    config_path: str | Path | None,
    extra_args: Sequence[str] = (),
    *,
    timeout_s: float = DEFAULT_SPAWN_TIMEOUT_S,
    log_path: str | Path | None = None,
) -> tuple[subprocess.Popen[bytes], dict[str, Any]]:
    """Start ``python -m sim_devices.launcher --json --stdin-watch`` and return (process, channels).

    The simulator runs in its own session (a terminal Ctrl-C reaches only the caller, which stops it with
    ``stop_sim_subprocess``) and exits by itself if the caller dies (its stdin closes). Its stderr goes to
    ``log_path`` (with ``--verbose``) or a temporary file. SimStartError, with the simulator's stderr, if it
    exits or prints no channels within ``timeout_s``.
    """
    cmd = [sys.executable, "-m", "sim_devices.launcher", "--json", "--stdin-watch"]
    if config_path is not None:
        cmd += ["--config", str(config_path)]
    if log_path is not None:
        cmd.append("--verbose")
    cmd += list(extra_args)
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join(p for p in (str(PROJECT_ROOT), env.get("PYTHONPATH")) if p)
    err_file: IO[bytes] = open(log_path, "w+b") if log_path is not None else tempfile.TemporaryFile()
    try:
        proc = subprocess.Popen(cmd, stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=err_file, env=env,
                                start_new_session=True)
        line = _read_first_line(proc, time.monotonic() + timeout_s)
        channels: dict[str, Any] | None = None
        if line is not None:
            with contextlib.suppress(ValueError):
                parsed = json.loads(line)
                channels = parsed if isinstance(parsed, dict) and "can" in parsed else None
        if channels is None:
            code = proc.poll()
            stop_sim_subprocess(proc)
            what = f"exited with code {code}" if code is not None else f"printed no channels within {timeout_s} s"
            raise SimStartError(f"the simulator ({' '.join(cmd[2:])}) {what}:\n{_tail(err_file)}")
    finally:
        err_file.close()
    log.info("sim_subprocess_started", pid=proc.pid, can=channels["can"]["channel"])
    return proc, channels


def stop_sim_subprocess(proc: subprocess.Popen[Any], timeout_s: float = 5.0) -> int:
    """SIGTERM, wait up to timeout_s (then SIGKILL), close the pipes; the exit code (negative: killed)."""
    if proc.poll() is None:
        proc.terminate()
        try:
            proc.wait(timeout_s)
        except subprocess.TimeoutExpired:
            log.warning("sim_subprocess_killed", pid=proc.pid)
            proc.kill()
            proc.wait()
    for pipe in (proc.stdin, proc.stdout):
        if pipe is not None:
            with contextlib.suppress(OSError):
                pipe.close()
    return cast(int, proc.returncode)


if __name__ == "__main__":
    sys.exit(main())
