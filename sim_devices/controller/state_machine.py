"""Simulated servo controller: state machine, rate-limited leg servo and parameter banks, transport-agnostic.

The model drives a ``SimulatedRig``. A leg setpoint L is a *controller length* (stroke + the controller's own
leg offset l0_ctrl from its live parameter set); the actuator moves to stroke s = L - l0_ctrl. The rig knows
lengths as "reported" = stroke + nominal l0 (robot file), so the servo calls ``rig.move_to_lengths(s + l0_nom)``
and reports s + l0_ctrl. Uploading compensated offsets therefore changes what the controller commands and
reports while the physics stays in ``rig.py``. With ``repeatability_mm`` each setpoint draws a settle error per leg
(seeded): the actuator stops that far from where its transducer reads, so the platform scatters from visit to visit
as a real machine's repeatability does, unseen by the controller. Time is real time multiplied by ``time_scale``
and the model advances lazily on every access, so it needs no thread of its own. All public methods are thread-safe.

This module knows no transport: ``can_peer.py`` + ``slcan_server.py`` / ``can_bus_server.py`` adapt it to CAN,
``modbus_protocol.py`` + ``modbus_server.py`` to Modbus, and ``controller_servers.py`` composes them.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Literal

import numpy as np
import structlog
from pydantic import BaseModel, ConfigDict, Field, model_validator

from hilcal.protocols.controller_states import (
    Command,
    ControllerState,
    FaultCode,
    RefusalReason,
    refusal_reason,
)
from hilcal.protocols.registers import (
    L0_INDEX,
    L0_REGISTERS,
    PARAMETER_COUNT,
    PARAMETER_REGISTERS,
    REGISTERS_PER_FLOAT,
    Capability,
    ParamCommand,
    ParamStatus,
    crc32_of_words,
    floats_from_words,
    parameter_limit_violations,
    words_from_floats,
)
from hilcal.robot import Robot
from sim_devices.rig.rig import SimulatedRig

log = structlog.get_logger(__name__)

N_LEGS = 6


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)


class CanFaultConfig(_Strict):
    """CAN fault injection active from start-up (rates are per frame, seeded)."""

    drop_rate: float = Field(default=0.0, ge=0, le=1)
    corrupt_rate: float = Field(default=0.0, ge=0, le=1)
    repeat_rate: float = Field(default=0.0, ge=0, le=1)
    delay_s: float = Field(default=0.0, ge=0, description="extra latency of every controller frame")
    heartbeat: bool = Field(default=True, description="False: the controller sends no Status/Feedback")
    seed: int = 0
    gaps_per_min: float = Field(default=0.0, ge=0, le=600,
                                description="link gaps at random times (Poisson): no controller frame is sent")
    gap_min_s: float = Field(default=0.05, gt=0, le=60, description="shortest gap, s (uniform between min and max)")
    gap_max_s: float = Field(default=0.5, gt=0, le=60, description="longest gap, s")
    gap_log: str | None = Field(default=None, description="JSONL file: every gap, and every frame received in one")
    gap_at_frames: list[int] = Field(default_factory=list, description="also start a gap when the controller has "
                                     "received this many frames (deterministic: the host sends only commands)")
    max_gaps: int | None = Field(default=None, ge=0, description="no gap after this many (counted in gap_log too, "
                                 "so a restarted simulator goes on counting)")

    @model_validator(mode="after")
    def _gap_range(self) -> CanFaultConfig:
        if self.gap_max_s < self.gap_min_s:
            raise ValueError(f"gap_max_s ({self.gap_max_s}) is below gap_min_s ({self.gap_min_s})")
        return self


class ModbusFaultConfig(_Strict):
    """Modbus fault injection active from start-up."""

    drop_after_writes: int | None = Field(
        default=None, ge=1, description="close the connection at this write request (1-based), once"
    )
    execute_dropped_write: bool = Field(
        default=False, description="True: the dropped write is executed before the connection closes"
    )
    exception_code: int | None = Field(default=None, ge=1, le=255, description="answer every request with this")
    response_delay_s: float = Field(default=0.0, ge=0, le=10, description="wait this long before every response")


class ControllerSimConfig(_Strict):
    """Everything that makes one simulated controller."""

    time_scale: float = Field(default=1.0, gt=0, description="simulated seconds per real second")
    leg_speed_mm_s: float = Field(default=50.0, gt=0)
    in_position_tolerance_mm: float = Field(default=0.005, gt=0)
    settle_s: float = Field(default=0.05, ge=0, description="all legs within tolerance this long -> IN_POSITION")
    heartbeat_period_s: float = Field(default=0.02, gt=0, description="real time, not scaled")
    capabilities: Literal["full", "offsets_only"] = "full"
    serial_number: int = Field(default=0x00C0FFEE, ge=0, le=0xFFFFFFFF)
    firmware_version: int = Field(default=0x0102, ge=0, le=0xFFFF)
    device_id: int = Field(default=1, ge=1, le=247)
    initial_fault: FaultCode = FaultCode.NONE
    estop_pressed: bool = False
    slcan_transport: Literal["pty", "tcp"] = "pty"
    modbus_port: int = Field(default=0, ge=0, le=65535, description="0: ephemeral port")
    modbus_rtu: bool = Field(default=False, description="also serve Modbus RTU on a pty")
    can_faults: CanFaultConfig = CanFaultConfig()
    modbus_faults: ModbusFaultConfig = ModbusFaultConfig()
    repeatability_mm: float = Field(default=0.0, ge=0, le=1.0, description="std of each leg's settle error per "
                                    "setpoint that its transducer does not see (the machine's repeatability), mm")
    repeatability_seed: int = Field(default=0, description="seed of the settle errors")


@dataclass(frozen=True)
class ControllerSnapshot:
    """What the controller reports at one instant."""

    state: ControllerState
    fault: FaultCode
    estop_input: bool
    lengths_mm: np.ndarray
    in_position: tuple[bool, ...]
    setpoint_tag: int
    setpoint_valid: bool
    fault_events: int


class StagingWriteRefused(Exception):
    """A staging write the controller's capabilities do not allow (mapped to a Modbus exception)."""


@dataclass
class _ParameterBanks:
    live: np.ndarray
    saved: np.ndarray
    backup: np.ndarray | None = None
    staging: list[int] = field(default_factory=list)
    written: set[int] = field(default_factory=set)
    staged_length: int = 0
    staged_crc_words: list[int] = field(default_factory=lambda: [0, 0])
    status: ParamStatus = ParamStatus.NO_COMMAND
    commit_counter: int = 0
    save_counter: int = 0


class SimulatedController:
    """Thread-safe controller model driving a SimulatedRig (see the module docstring)."""

    def __init__(
        self,
        robot: Robot,
        rig: SimulatedRig,
        config: ControllerSimConfig | None = None,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self.robot = robot
        self.config = config or ControllerSimConfig()
        self._rig = rig
        self._clock = clock
        self._lock = threading.RLock()
        lo, hi = robot.leg_limits
        self._l0_nominal = robot.l0
        self._stroke_min_mm = lo - robot.l0
        self._stroke_max_mm = hi - robot.l0
        nominal = np.concatenate([robot.a.ravel(), robot.b.ravel(), robot.l0]).astype(np.float32)
        self._banks = _ParameterBanks(live=nominal.copy(), saved=nominal.copy())
        self._banks.staging = words_from_floats(nominal.tolist())
        self._settle_rng = np.random.default_rng([self.config.repeatability_seed, 0x5E771E])
        self._settle_error_mm = np.zeros(N_LEGS)
        self._stroke_mm = rig.reported_lengths() - self._l0_nominal
        self._target_mm = self._stroke_mm.copy()
        self._settled_s = 0.0
        self._setpoint_tag = 0
        self._setpoint_valid = False
        self._estop_input = self.config.estop_pressed
        self._fault = FaultCode.NONE
        self._fault_events = 0
        self._state = ControllerState.DISABLED
        if self.config.estop_pressed:
            self._enter_stop_state(ControllerState.ESTOP, FaultCode.ESTOP_INPUT)
        elif self.config.initial_fault is not FaultCode.NONE:
            self._enter_stop_state(ControllerState.FAULT, self.config.initial_fault)
        self._last_update = clock()

    # ------------------------------------------------------------------ servo

    @property
    def capabilities(self) -> Capability:
        base = Capability.NONVOLATILE_SAVE | Capability.ROLLBACK
        if self.config.capabilities == "full":
            return base | Capability.FULL_GEOMETRY
        return base | Capability.OFFSETS_ONLY

    def _l0_ctrl(self) -> np.ndarray:
        return self._banks.live[L0_INDEX:].astype(float)

    def _measured_stroke(self) -> np.ndarray:
        """The transducers' reading: the actuators' position less the settle error they do not see."""
        return self._rig.reported_lengths() - self._l0_nominal - self._settle_error_mm

    def _update(self) -> None:
        now = self._clock()
        dt_s = max(0.0, now - self._last_update) * self.config.time_scale
        self._last_update = now
        if self._state not in (ControllerState.MOVING, ControllerState.IN_POSITION) or dt_s == 0.0:
            return
        error = self._target_mm - self._stroke_mm
        step = self.config.leg_speed_mm_s * dt_s
        arrive_s = float(np.max(np.abs(error))) / self.config.leg_speed_mm_s
        stroke = np.clip(self._stroke_mm + np.clip(error, -step, step), self._stroke_min_mm, self._stroke_max_mm)
        if not np.array_equal(stroke, self._stroke_mm):
            # Legs that did not move leave the rig alone: it keeps its solved pose instead of solving it again.
            self._stroke_mm = stroke
            self._rig.move_to_lengths(np.clip(self._stroke_mm + self._settle_error_mm + self._l0_nominal,
                                          *self.robot.leg_limits))
        if all(self._in_position()):
            self._settled_s += max(0.0, dt_s - arrive_s)
            if self._state is ControllerState.MOVING and self._settled_s >= self.config.settle_s:
                self._state = ControllerState.IN_POSITION
        else:
            self._settled_s = 0.0
            self._state = ControllerState.MOVING

    def _in_position(self) -> list[bool]:
        error = np.abs(self._target_mm - self._measured_stroke())
        return [bool(e <= self.config.in_position_tolerance_mm) for e in error]

    def _hold(self) -> None:
        """Stop motion where the legs are now."""
        self._stroke_mm = self._measured_stroke()
        self._target_mm = self._stroke_mm.copy()
        self._settled_s = 0.0

    def _enter_stop_state(self, state: ControllerState, fault: FaultCode) -> None:
        self._hold()
        if self._state is not state or self._fault is not fault:
            self._fault_events += 1
        self._state = state
        self._fault = fault
        self._setpoint_valid = False
        log.info("controller_stopped", state=state.name, fault=fault.name)

    def snapshot(self) -> ControllerSnapshot:
        """State, fault and measured controller lengths (stroke + controller l0) now."""
        with self._lock:
            self._update()
            motion = self._state in (ControllerState.MOVING, ControllerState.IN_POSITION)
            in_position = tuple(self._in_position()) if motion else (False,) * N_LEGS
            return ControllerSnapshot(
                state=self._state,
                fault=self._fault,
                estop_input=self._estop_input,
                lengths_mm=self._measured_stroke() + self._l0_ctrl(),
                in_position=in_position,
                setpoint_tag=self._setpoint_tag,
                setpoint_valid=self._setpoint_valid,
                fault_events=self._fault_events,
            )

    @property
    def state(self) -> ControllerState:
        return self.snapshot().state

    def command(self, command: Command) -> RefusalReason:
        """Execute ENABLE / DISABLE / STOP / FAULT_RESET if the state machine allows it."""
        if command is Command.SETPOINT:
            return RefusalReason.UNKNOWN_COMMAND
        with self._lock:
            self._update()
            reason = refusal_reason(self._state, command)
            if reason is RefusalReason.ACCEPTED and command is Command.FAULT_RESET and self._estop_input:
                reason = RefusalReason.ESTOP_NOT_RELEASED
            if reason is not RefusalReason.ACCEPTED:
                log.info("command_refused", command=command.name, state=self._state.name, reason=reason.name)
                return reason
            self._hold()
            if command is Command.ENABLE:
                self._state = ControllerState.ENABLED
            elif command is Command.DISABLE:
                self._state = ControllerState.DISABLED
                self._setpoint_valid = False
            elif command is Command.STOP:
                self._state = ControllerState.ENABLED
            else:
                self._state = ControllerState.DISABLED
                self._fault = FaultCode.NONE
            log.info("command_accepted", command=command.name, state=self._state.name)
            return RefusalReason.ACCEPTED

    def set_setpoint(self, lengths_mm: Sequence[float], tag: int = 0) -> RefusalReason:
        """Start moving to controller lengths (mm) if enabled and within the stroke range; tag is echoed."""
        target = np.asarray(lengths_mm, dtype=float)
        if target.shape != (N_LEGS,):
            return RefusalReason.SETPOINT_INCOMPLETE
        with self._lock:
            self._update()
            reason = refusal_reason(self._state, Command.SETPOINT)
            if reason is not RefusalReason.ACCEPTED:
                return reason
            stroke = target - self._l0_ctrl()
            if not (np.isfinite(stroke).all() and (stroke >= self._stroke_min_mm).all()
                    and (stroke <= self._stroke_max_mm).all()):
                log.info("setpoint_refused", lengths_mm=target.tolist())
                return RefusalReason.SETPOINT_OUT_OF_LIMITS
            self._stroke_mm = self._measured_stroke()
            if self.config.repeatability_mm > 0:
                self._settle_error_mm = self._settle_rng.normal(0.0, self.config.repeatability_mm, N_LEGS)
                self._rig.move_to_lengths(np.clip(self._stroke_mm + self._settle_error_mm + self._l0_nominal,
                                                  *self.robot.leg_limits))
            self._target_mm = stroke
            self._settled_s = 0.0
            self._setpoint_tag = tag
            self._setpoint_valid = True
            self._state = ControllerState.MOVING
            return RefusalReason.ACCEPTED

    def inject_fault(self, code: FaultCode = FaultCode.DRIVE) -> None:
        """A controller fault: motion stops, state FAULT until FAULT_RESET."""
        with self._lock:
            self._update()
            self._enter_stop_state(ControllerState.FAULT, code)

    def press_estop(self, source: Literal["input", "request"] = "input") -> None:
        """E-stop: the hardware input (stays pressed until release_estop) or a one-shot software request."""
        with self._lock:
            self._update()
            if source == "input":
                self._estop_input = True
            fault = FaultCode.ESTOP_INPUT if source == "input" else FaultCode.ESTOP_REQUEST
            if self._state is not ControllerState.ESTOP:
                self._enter_stop_state(ControllerState.ESTOP, fault)

    def release_estop(self) -> None:
        """Release the hardware e-stop input; the controller stays in ESTOP until FAULT_RESET."""
        with self._lock:
            self._estop_input = False

    def true_pose(self) -> np.ndarray:
        """Actual platform pose of the rig (mm, deg), read under the model lock."""
        with self._lock:
            self._update()
            return self._rig.true_pose()

    def strokes_mm(self) -> np.ndarray:
        """Physical actuator strokes (mm) measured now."""
        with self._lock:
            self._update()
            return self._measured_stroke()

    # ------------------------------------------------------------------ parameter banks

    def install_parameters(self, values: Sequence[float]) -> None:
        """Service-tool path for simulator set-up: replace live and saved sets without a transaction."""
        v = np.asarray(values, dtype=np.float32)
        if v.shape != (PARAMETER_COUNT,) or parameter_limit_violations(v.tolist()):
            raise ValueError(f"not a valid {PARAMETER_COUNT}-value parameter set")
        with self._lock:
            self._banks.live = v.copy()
            self._banks.saved = v.copy()
            self._banks.backup = None

    def restore_banks(self, live: Sequence[float], saved: Sequence[float], backup: Sequence[float] | None,
                      commit_counter: int, save_counter: int) -> None:
        """Put back parameter banks kept outside the process (non-volatile state across a restart)."""
        with self._lock:
            b = self._banks
            b.live = np.asarray(live, dtype=np.float32)
            b.saved = np.asarray(saved, dtype=np.float32)
            b.backup = None if backup is None else np.asarray(backup, dtype=np.float32)
            b.staging = words_from_floats(b.live.tolist())
            b.commit_counter = commit_counter
            b.save_counter = save_counter

    def live_parameters(self) -> np.ndarray:
        with self._lock:
            return self._banks.live.astype(float)

    def backup_parameters(self) -> np.ndarray | None:
        with self._lock:
            return None if self._banks.backup is None else self._banks.backup.astype(float)

    def saved_parameters(self) -> np.ndarray:
        with self._lock:
            return self._banks.saved.astype(float)

    def bank_words(self, bank: Literal["live", "backup", "saved", "staging"]) -> list[int]:
        """A bank as 84 registers (ABCD float32); a missing backup reads as zeros."""
        with self._lock:
            if bank == "staging":
                return list(self._banks.staging)
            values = getattr(self._banks, bank)
            if values is None:
                return [0] * PARAMETER_REGISTERS
            return words_from_floats(values.tolist())

    def bank_crc32(self, bank: Literal["live", "backup", "saved"]) -> int:
        with self._lock:
            if bank == "backup" and self._banks.backup is None:
                return 0
            return crc32_of_words(self.bank_words(bank))

    def param_registers(self) -> dict[str, int]:
        """Status, counters and staging header as register values."""
        with self._lock:
            b = self._banks
            return {
                "status": int(b.status),
                "commit_counter": b.commit_counter & 0xFFFF,
                "save_counter": b.save_counter & 0xFFFF,
                "staged_written": len(b.written),
                "staged_length": b.staged_length,
                "staged_crc_hi": b.staged_crc_words[0],
                "staged_crc_lo": b.staged_crc_words[1],
            }

    def write_staging(self, offset: int, words: Sequence[int]) -> None:
        """Write registers into the staging bank (offset in registers); offsets-only allows the l0 part only."""
        if offset < 0 or offset + len(words) > PARAMETER_REGISTERS:
            raise StagingWriteRefused(f"staging offset {offset}+{len(words)} is outside 0..{PARAMETER_REGISTERS}")
        l0_start = L0_INDEX * REGISTERS_PER_FLOAT
        if self.config.capabilities == "offsets_only" and offset < l0_start:
            raise StagingWriteRefused("offsets-only controller: a/b staging registers are read-only")
        with self._lock:
            for k, w in enumerate(words):
                self._banks.staging[offset + k] = int(w) & 0xFFFF
                self._banks.written.add(offset + k)

    def write_staging_header(self, length: int | None = None, crc_words: Sequence[int | None] = (None, None)) -> None:
        """Set STAGED_LENGTH and/or the two STAGED_CRC32 words (None leaves a value unchanged)."""
        with self._lock:
            if length is not None:
                self._banks.staged_length = int(length) & 0xFFFF
            for k, w in enumerate(crc_words):
                if w is not None:
                    self._banks.staged_crc_words[k] = int(w) & 0xFFFF

    def param_command(self, command: ParamCommand) -> ParamStatus:
        """OPEN_STAGING / COMMIT / ROLLBACK / SAVE; every command needs the controller DISABLED."""
        with self._lock:
            self._update()
            status = self._param_command(command)
            self._banks.status = status
            log.info("param_command", command=command.name, status=status.name)
            return status

    def _param_command(self, command: ParamCommand) -> ParamStatus:
        b = self._banks
        if self._state is not ControllerState.DISABLED:
            return ParamStatus.NOT_DISABLED
        if command is ParamCommand.OPEN_STAGING:
            b.staging = words_from_floats(b.live.tolist())
            b.written.clear()
            b.staged_length = 0
            b.staged_crc_words = [0, 0]
            return ParamStatus.OK
        if command is ParamCommand.SAVE:
            b.saved = b.live.copy()
            b.save_counter += 1
            return ParamStatus.OK
        if command is ParamCommand.ROLLBACK:
            if b.backup is None:
                return ParamStatus.NO_BACKUP
            b.live, b.backup = b.backup, b.live
            b.commit_counter += 1
            return ParamStatus.OK
        return self._commit()

    def _commit(self) -> ParamStatus:
        b = self._banks
        l0_start = L0_INDEX * REGISTERS_PER_FLOAT
        offsets_only = self.config.capabilities == "offsets_only"
        required = set(range(l0_start, l0_start + L0_REGISTERS)) if offsets_only else set(range(PARAMETER_REGISTERS))
        if not required <= b.written:
            return ParamStatus.INCOMPLETE_STAGING
        if b.staged_length != len(b.written):
            return ParamStatus.LENGTH_MISMATCH
        if crc32_of_words(b.staging) != (b.staged_crc_words[0] << 16 | b.staged_crc_words[1]):
            return ParamStatus.CRC_MISMATCH
        values = np.asarray(floats_from_words(b.staging), dtype=np.float32)
        if not np.isfinite(values).all():
            return ParamStatus.NOT_FINITE
        if parameter_limit_violations(values.tolist()):
            return ParamStatus.LIMIT_VIOLATION
        if offsets_only and not np.array_equal(values[:L0_INDEX], b.live[:L0_INDEX]):
            return ParamStatus.CAPABILITY_VIOLATION
        b.backup, b.live = b.live, values
        b.commit_counter += 1
        b.written.clear()
        b.staged_length = 0
        b.staged_crc_words = [0, 0]
        log.info("parameters_committed", crc32=hex(crc32_of_words(words_from_floats(values.tolist()))))
        return ParamStatus.OK
