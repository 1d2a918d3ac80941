"""The simulator's persistent state: parameter banks, leg lengths, motion directions and clock in a locked file.

With a ``state_file`` the controller's parameter banks (live, backup, saved), the rig's reported leg lengths,
motion directions and clock are written atomically (temp file + ``os.replace``) and loaded at start: a simulator
restarted on the same file finds the controller as it was (powered up DISABLED, like a real controller after a
power cycle). A bank change is written and fsynced before it is acknowledged on the wire (it survives a power cut,
like a controller's NVRAM); leg motion is written at most every MOTION_SAVE_PERIOD_S (see PersistentController).
"""

from __future__ import annotations

import fcntl
import os
import struct
import time
from collections.abc import Sequence
from datetime import UTC, datetime
from pathlib import Path
from typing import Annotated, Any, Literal

import numpy as np
import structlog
from pydantic import BaseModel, ConfigDict, Field, ValidationError

from hilcal.protocols.controller_states import Command, FaultCode, RefusalReason
from hilcal.protocols.registers import ParamCommand, ParamStatus
from hilcal.robot import Robot
from sim_devices.controller.state_machine import ControllerSimConfig, ControllerSnapshot, SimulatedController
from sim_devices.rig.rig import SimulatedRig
from sim_devices.sim_config import format_validation_errors

log = structlog.get_logger(__name__)


STATE_FORMAT = "hilcal-sim-state"
STATE_VERSION = 1
MOTION_SAVE_PERIOD_S = 0.2
"""Leg lengths, motion directions and the controller state are saved at most this often (real time); banks at once."""
CLOCK_STEP_S = 10.0
"""The rig clock follows simulated time in steps of this many simulated seconds."""
DIRECTION_STEP_MM = 0.002
DEFAULT_LOCK_TIMEOUT_S = 5.0


class SimStateError(RuntimeError):
    """The state file cannot be used: unreadable, for another robot, or held by another simulator."""


Floats42 = Annotated[list[float], Field(min_length=42, max_length=42)]
Floats6 = Annotated[list[float], Field(min_length=6, max_length=6)]


class BankState(BaseModel):
    """The controller's parameter banks (float32 values, stored exactly), its compensation banks (registers as hex,
    None: the factory block) and counters."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    live: Floats42
    backup: Floats42 | None
    saved: Floats42
    commit_counter: int
    save_counter: int
    comp_live: str | None = None
    comp_backup: str | None = None
    comp_saved: str | None = None

    def compensation_words(self) -> dict[str, list[int] | None]:
        """The compensation banks as registers (None where the file holds none)."""
        return {bank: None if text is None else list(struct.unpack(f">{len(text) // 4}H", bytes.fromhex(text)))
                for bank, text in (("live", self.comp_live), ("backup", self.comp_backup),
                                   ("saved", self.comp_saved))}


def _hex(words: list[int] | None) -> str | None:
    return None if words is None else struct.pack(f">{len(words)}H", *words).hex()


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
            raise SimStateError(format_validation_errors(err, f"state file {self.path}")) from None
        if state.robot != self.robot_name:
            raise SimStateError(
                f"state file {self.path} is for robot {state.robot!r}, the simulator runs {self.robot_name!r}"
            )
        self.sequence = state.sequence
        return state

    def write(self, state: SimState, durable: bool = True) -> None:
        """Replace the file atomically (temp file, os.replace): a killed simulator leaves the old or the new file.

        durable: fsync first, so the file also survives a power cut (the parameter banks, a controller's NVRAM);
        leg lengths and states change on every move and need only the atomic replace.
        """
        tmp = self.path.with_name(f".{self.path.name}.{os.getpid()}.tmp")
        with open(tmp, "w") as fh:
            fh.write(state.model_dump_json(indent=1))
            fh.flush()
            if durable:
                os.fsync(fh.fileno())
        os.replace(tmp, self.path)

    def close(self) -> None:
        """Release the lock (idempotent); the state file stays."""
        if self._lock_fd >= 0:
            os.close(self._lock_fd)
            self._lock_fd = -1


def restore_rig(rig: SimulatedRig, state: RigState) -> None:
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
    returning, i.e. before the change is acknowledged on CAN or Modbus) when the banks changed; changes of the
    legs and the state alone at most every MOTION_SAVE_PERIOD_S (the heartbeat's snapshots write the last one),
    so a move is not slowed by a file write. A killed simulator restarts with its banks exactly as acknowledged
    and its legs as they were at most that long before; a stopped one saves everything on close.
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
        self._bank_state: tuple[int, BankState] | None = None
        if banks is not None:
            self.restore_banks(banks.live, banks.saved, banks.backup, banks.commit_counter, banks.save_counter,
                               banks.compensation_words())

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
            return SimState(
                robot=self.robot.name,
                written_at=datetime.now(UTC).isoformat(timespec="milliseconds"),
                sequence=self._store.sequence + 1 if self._store is not None else 0,
                controller_state=snap.state.name,
                banks=self._banks_state(),
                rig=RigState(
                    reported_lengths_mm=self._sim_rig.reported_lengths().tolist(),
                    direction=self._sim_rig.motion_direction().tolist(),
                    time_s=self._sim_rig.time_s,
                ),
            )

    def _banks_state(self) -> BankState:
        """The banks as the file holds them, rebuilt only when a bank changed (the heartbeat reads this often)."""
        if self._bank_state is None or self._bank_state[0] != self.banks_version:
            backup = self.backup_parameters()
            registers = self.param_registers()
            self._bank_state = (self.banks_version, BankState(
                live=self.live_parameters().tolist(),
                backup=None if backup is None else backup.tolist(),
                saved=self.saved_parameters().tolist(),
                commit_counter=registers["commit_counter"],
                save_counter=registers["save_counter"],
                comp_live=_hex(self.comp_words("live")),
                comp_backup=None if backup is None else _hex(self.comp_words("backup")),
                comp_saved=_hex(self.comp_words("saved")),
            ))
        return self._bank_state[1]

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
                same_banks = self._saved_key is not None and state.banks == self._saved_key[1]
                if same_banks and now - self._saved_at < MOTION_SAVE_PERIOD_S:
                    return
            banks_changed = self._saved_key is None or state.banks != self._saved_key[1]
            self._store.write(state, durable=force or banks_changed)
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
