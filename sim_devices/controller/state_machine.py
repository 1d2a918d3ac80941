"""Simulated servo controller: state machine, rate-limited leg servo and parameter banks, transport-agnostic.

The model drives a ``SimulatedRig``. A leg setpoint L is a *controller length* (stroke + the controller's own
leg offset l0_ctrl from its live parameter set); the actuator moves to stroke s = L - l0_ctrl. The rig knows
lengths as "reported" = stroke + nominal l0 (robot file), so the servo calls ``rig.move_to_lengths(s + l0_nom)``
and reports s + l0_ctrl. Uploading compensated offsets therefore changes what the controller commands and
reports while the physics stays in ``rig.py``. With ``repeatability_mm`` each setpoint draws a settle error per leg
(seeded): the actuator stops that far from where its transducer reads, so the platform scatters from visit to visit
as a real machine's repeatability does, unseen by the controller. A leg in ``dead_transducer_legs`` reads a
fixed length whatever its actuator does; the servo drives it on past its target while its reading lags, and the
following-error monitor (``following_error_mm``) stops the move with FOLLOWING_ERROR once the ramp has driven
that actuator that far from its reading, as a real servo controller's does. Time is real time multiplied by
``time_scale`` and the model advances lazily on every access, so it needs no thread of its own. All public methods
are thread-safe.

This module knows no transport: ``can_peer.py`` + ``slcan_server.py`` / ``can_bus_server.py`` adapt it to CAN,
``modbus_protocol.py`` + ``modbus_server.py`` to Modbus, and ``controller_servers.py`` composes them.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Literal

import numpy as np
import structlog

from hilcal.protocols.controller_states import (
    Command,
    ControllerState,
    FaultCode,
    RefusalReason,
    refusal_reason,
)
from hilcal.protocols.registers import (
    L0_INDEX,
    PROTOCOL_VERSION,
    PROTOCOL_VERSION_1_0,
    Capability,
    ParamCommand,
    ParamStatus,
)
from hilcal.robot import Robot
from sim_devices.controller.config import CanFaultConfig, ControllerSimConfig, ModbusFaultConfig
from sim_devices.controller.leg_corrector import LegCorrector
from sim_devices.controller.parameter_banks import Bank, BankCapabilities, ParameterBanks
from sim_devices.rig.rig import SimulatedRig

__all__ = ["CanFaultConfig", "ControllerSimConfig", "ControllerSnapshot", "ModbusFaultConfig", "SimulatedController"]

log = structlog.get_logger(__name__)

N_LEGS = 6
DIRECTION_DEADBAND_MM = 1e-3
"""A setpoint that moves a leg by less than this keeps the leg's direction of motion (as the compensation block's
backlash term defines it)."""
RETARGET_TOLERANCE_MM = 1e-5
"""After the legs arrive, the block's force terms are evaluated at the reached pose; a target that moves by more
than this is driven to (the servo loop closes on the corrected length)."""
MAX_RETARGETS = 5


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
        cfg = self.config
        self._banks = ParameterBanks(live=nominal.copy(), saved=nominal.copy(), capabilities=BankCapabilities(
            offsets_only=cfg.capabilities == "offsets_only", compensation=cfg.compensation,
            force_reading=cfg.compensation and cfg.force_reading,
            temperature_reading=cfg.compensation and cfg.temperature_reading))
        self._corrector: tuple[int, LegCorrector | None] = (-1, None)
        self._direction = rig.motion_direction()
        self._force_kn = np.zeros(N_LEGS)
        self._temperature_c = 20.0
        self._temperature_at_s: float | None = None
        self._setpoint_mm = np.full(N_LEGS, np.nan)
        self._retargets = 0
        self._settle_rng = np.random.default_rng([self.config.repeatability_seed, 0x5E771E])
        self._settle_error_mm = np.zeros(N_LEGS)
        self._dead = np.isin(np.arange(1, N_LEGS + 1), self.config.dead_transducer_legs)
        self._power_up_stroke_mm = self._actuator_stroke()
        self._slip_mm = np.zeros(N_LEGS)
        self._stroke_mm = np.zeros(N_LEGS)
        self._rebase()
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
        caps = Capability.NONVOLATILE_SAVE | Capability.ROLLBACK
        caps |= Capability.FULL_GEOMETRY if self.config.capabilities == "full" else Capability.OFFSETS_ONLY
        bank = self._banks.capabilities
        if bank.compensation:
            caps |= Capability.COMPENSATION
        if bank.force_reading:
            caps |= Capability.FORCE_READING
        if bank.temperature_reading:
            caps |= Capability.TEMPERATURE_READING
        return caps

    @property
    def protocol_version(self) -> int:
        return PROTOCOL_VERSION if self.config.compensation else PROTOCOL_VERSION_1_0

    def _l0_ctrl(self) -> np.ndarray:
        return self._banks.live[L0_INDEX:].astype(float)

    def _live_corrector(self) -> LegCorrector | None:
        """The live compensation block (None when it corrects nothing), decoded once per bank change."""
        if self._corrector[0] != self._banks.version:
            corrector = LegCorrector(self._banks.live_block())
            self._corrector = (self._banks.version, corrector if corrector.active else None)
        return self._corrector[1]

    def _read_sensors(self, corrector: LegCorrector) -> None:
        """Sample the force and temperature readings the block's terms use (at the platform's pose now)."""
        if corrector.needs_force:
            self._force_kn = self._rig.leg_forces_kn()
        if corrector.needs_temperature:
            self._temperature_c = self._filtered_temperature_c()

    def _filtered_temperature_c(self) -> float:
        """The temperature the block uses: the sensor's reading low-pass filtered over the rig's clock (a leg's
        temperature changes over minutes; a controller does not let sensor noise into every setpoint)."""
        reading, now = self._rig.temperature_c(), self._rig.time_s
        if self._temperature_at_s is None:
            self._temperature_c = reading
        else:
            weight = 1.0 - np.exp(-max(now - self._temperature_at_s, 0.0) / self.config.temperature_filter_s)
            self._temperature_c += weight * (reading - self._temperature_c)
        self._temperature_at_s = now
        return self._temperature_c

    def _reported(self, stroke_mm: np.ndarray) -> np.ndarray:
        """Leg lengths as reported: l0 + raw stroke, corrected by the live block with the last sensor readings."""
        corrector = self._live_corrector()
        if corrector is None:
            return stroke_mm + self._l0_ctrl()
        return corrector.length_mm(stroke_mm, self._l0_ctrl(), self._force_kn, self._direction, self._temperature_c)

    def _stroke_target(self, lengths_mm: np.ndarray) -> np.ndarray:
        """The raw strokes the servo drives to for a setpoint of these (corrected) lengths."""
        corrector = self._live_corrector()
        if corrector is None:
            return lengths_mm - self._l0_ctrl()
        return corrector.stroke_for(lengths_mm, self._l0_ctrl(), self._force_kn, self._direction, self._temperature_c)

    def _retarget(self) -> None:
        """Legs at their target: read the sensors at the reached pose and correct the target (the servo loop closes
        on the corrected length, so a force term evaluated at the pose before the move is refined here)."""
        corrector = self._live_corrector()
        if corrector is None or not (corrector.needs_force or corrector.needs_temperature):
            return
        if self._retargets >= MAX_RETARGETS or not np.array_equal(self._stroke_mm, self._target_mm):
            return
        self._read_sensors(corrector)
        target = np.clip(self._stroke_target(self._setpoint_mm), self._stroke_min_mm, self._stroke_max_mm)
        self._retargets += 1
        if float(np.max(np.abs(target - self._target_mm))) > RETARGET_TOLERANCE_MM:
            self._target_mm = target
            self._settled_s = 0.0

    def _actuator_stroke(self) -> np.ndarray:
        """Where the actuators are, as a sound transducer reads them: less the settle error it does not see."""
        return self._rig.reported_lengths() - self._l0_nominal - self._settle_error_mm

    def _reading(self, actuator_stroke_mm: np.ndarray) -> np.ndarray:
        """What the transducers read with the actuators at these strokes: the strokes, but a dead one's fixed value."""
        stroke = np.array(actuator_stroke_mm, dtype=float)
        if self._dead.any():
            dead_mm = self.config.dead_reading_mm
            fixed = self._power_up_stroke_mm if dead_mm is None else dead_mm - self._l0_ctrl()
            stroke[self._dead] = fixed[self._dead]
        return stroke

    def _measured_stroke(self) -> np.ndarray:
        """The transducers' reading now."""
        return self._reading(self._actuator_stroke())

    def _rebase(self) -> None:
        """Start the servo's ramp from the readings (as a servo does); a leg whose reading is not where its actuator
        is keeps the difference as slip, so the actuator does not jump."""
        measured = self._measured_stroke()
        self._slip_mm = self._actuator_stroke() - measured
        self._stroke_mm = measured

    def _move_actuators(self) -> None:
        self._rig.move_to_lengths(np.clip(self._stroke_mm + self._slip_mm + self._settle_error_mm + self._l0_nominal,
                                          *self.robot.leg_limits))

    def _following_error_s(self, error: np.ndarray, dt_s: float) -> tuple[float, list[int]] | None:
        """When within the next dt_s the ramp first takes a leg more than ``following_error_mm`` from its reading
        (s from now) and the legs (1-based) it does that to; None if it does not. Only a leg whose reading does not
        follow its actuator can get there: a sound one reads the ramp less a settle error below 1 mm."""
        limit, speed = self.config.following_error_mm, self.config.leg_speed_mm_s
        step = speed * dt_s
        ramp = self._stroke_mm + np.clip(error, -step, step)
        reading = self._reading(ramp + self._slip_mm)  # the actuators follow the ramp
        over = np.abs(ramp - reading) > limit
        if not over.any():
            return None
        now = self._stroke_mm - reading  # a reading that did not follow stood still
        # Within the limit now, the ramp leaves it through reading + sign(error) * limit (it moves one way only).
        t = np.where(over, np.where(np.abs(now) > limit, 0.0, (limit - np.sign(error) * now) / speed), np.inf)
        first = float(np.min(t))
        return min(max(first, 0.0), dt_s), [int(i) + 1 for i in np.flatnonzero(t <= first + 1e-12)]

    def _update(self) -> None:
        now = self._clock()
        dt_s = max(0.0, now - self._last_update) * self.config.time_scale
        self._last_update = now
        if self._state not in (ControllerState.MOVING, ControllerState.IN_POSITION) or dt_s == 0.0:
            return
        error = self._target_mm - self._stroke_mm
        # A leg that will not read its target when its ramp gets there is driven on past it (the loop integrates its
        # error): a sound leg reads its ramp, a dead one runs on to the following-error limit.
        short = self._target_mm - self._reading(self._target_mm + self._slip_mm)
        driven_on = np.abs(short) > self.config.in_position_tolerance_mm
        error = np.where(driven_on, np.sign(short) * (self.config.leg_speed_mm_s * dt_s + 1.0), error)
        trip = self._following_error_s(error, dt_s)
        step = self.config.leg_speed_mm_s * (dt_s if trip is None else trip[0])
        arrive_s = float(np.max(np.abs(error))) / self.config.leg_speed_mm_s
        # The actuator (ramp + slip) stays within the stroke.
        stroke = np.clip(self._stroke_mm + np.clip(error, -step, step), self._stroke_min_mm - self._slip_mm,
                         self._stroke_max_mm - self._slip_mm)
        if not np.array_equal(stroke, self._stroke_mm):
            # Legs that did not move leave the rig alone: it keeps its solved pose instead of solving it again.
            self._stroke_mm = stroke
            self._move_actuators()
        if trip is not None:
            self._following_error(trip[1])
            return
        if self._state is ControllerState.MOVING:
            self._retarget()
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
        self._rebase()
        self._target_mm = self._stroke_mm.copy()
        self._settled_s = 0.0

    def _following_error(self, legs: list[int]) -> None:
        """The ramp is more than ``following_error_mm`` from these legs' readings: FAULT, hold where the legs are."""
        reading = self._measured_stroke()
        log.warning("controller_following_error", legs=legs, reading_mm=self._reported(reading).round(3).tolist(),
                    ramp_minus_reading_mm=(self._stroke_mm - reading).round(3).tolist())
        self._enter_stop_state(ControllerState.FAULT, FaultCode.FOLLOWING_ERROR)

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
                lengths_mm=self._reported(self._measured_stroke()),
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
            if not np.isfinite(target).all():
                log.info("setpoint_refused", lengths_mm=target.tolist())
                return RefusalReason.SETPOINT_OUT_OF_LIMITS
            corrector = self._live_corrector()
            direction = self._direction
            if corrector is not None:
                step = target - self._reported(self._measured_stroke())
                direction = np.where(np.abs(step) >= DIRECTION_DEADBAND_MM, np.sign(step), self._direction)
                self._read_sensors(corrector)
            previous, self._direction = self._direction, direction
            stroke = self._stroke_target(target)
            if not ((stroke >= self._stroke_min_mm).all() and (stroke <= self._stroke_max_mm).all()):
                self._direction = previous
                log.info("setpoint_refused", lengths_mm=target.tolist())
                return RefusalReason.SETPOINT_OUT_OF_LIMITS
            self._setpoint_mm = target
            self._retargets = 0
            self._rebase()
            if self.config.repeatability_mm > 0:
                self._settle_error_mm = self._settle_rng.normal(0.0, self.config.repeatability_mm, N_LEGS)
                self._move_actuators()
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
        with self._lock:
            self._banks.install(values)

    def restore_banks(self, live: Sequence[float], saved: Sequence[float], backup: Sequence[float] | None,
                      commit_counter: int, save_counter: int, comp: dict[str, list[int] | None] | None = None
                      ) -> None:
        """Put back parameter banks kept outside the process (non-volatile state across a restart)."""
        with self._lock:
            self._banks.restore(live, saved, backup, commit_counter, save_counter, comp)

    @property
    def banks_version(self) -> int:
        """Changes whenever a live, backup or saved bank does."""
        return self._banks.version

    def live_parameters(self) -> np.ndarray:
        with self._lock:
            return self._banks.live.astype(float)

    def backup_parameters(self) -> np.ndarray | None:
        with self._lock:
            return None if self._banks.backup is None else self._banks.backup.astype(float)

    def saved_parameters(self) -> np.ndarray:
        with self._lock:
            return self._banks.saved.astype(float)

    def live_compensation(self) -> dict:
        """The live compensation block, decoded (hilcal.protocols.compensation's layout)."""
        with self._lock:
            return self._banks.live_block()

    def bank_words(self, bank: Bank) -> list[int]:
        """A geometry bank as 84 registers (ABCD float32); a missing backup reads as zeros."""
        with self._lock:
            return self._banks.words(bank)

    def bank_crc32(self, bank: Literal["live", "backup", "saved"]) -> int:
        with self._lock:
            return self._banks.crc32(bank)

    def comp_words(self, bank: Bank) -> list[int]:
        """A compensation bank as registers; a missing backup reads as zeros."""
        with self._lock:
            return self._banks.comp_words(bank)

    def comp_crc32(self, bank: Literal["live", "backup", "saved"]) -> int:
        with self._lock:
            return self._banks.comp_crc32(bank)

    def leg_forces_reading(self) -> np.ndarray:
        """The axial leg compressions (kN) the controller reads now (its pressure sensors: the rig's statics)."""
        with self._lock:
            self._update()
            return self._rig.leg_forces_kn()

    def temperature_reading(self) -> float:
        """The leg temperature (°C) the controller reads now."""
        with self._lock:
            return self._rig.temperature_c()

    def param_registers(self) -> dict[str, int]:
        """Status, counters and staging header as register values."""
        with self._lock:
            b = self._banks
            return {
                "status": int(b.status),
                "commit_counter": b.commit_counter & 0xFFFF,
                "save_counter": b.save_counter & 0xFFFF,
                "staged_written": len(b.written) + len(b.comp_written),
                "staged_length": b.staged_length,
                "staged_crc_hi": b.staged_crc_words[0],
                "staged_crc_lo": b.staged_crc_words[1],
                "staged_comp_crc_hi": b.staged_comp_crc_words[0],
                "staged_comp_crc_lo": b.staged_comp_crc_words[1],
            }

    def write_staging(self, offset: int, words: Sequence[int]) -> None:
        """Write registers into the staging bank (offset in registers); offsets-only allows the l0 part only."""
        with self._lock:
            self._banks.write_staging(offset, words)

    def write_comp_staging(self, offset: int, words: Sequence[int]) -> None:
        """Write registers into the compensation staging bank (offset in registers)."""
        with self._lock:
            self._banks.write_comp_staging(offset, words)

    def write_staging_header(self, length: int | None = None, crc_words: Sequence[int | None] = (None, None),
                             comp_crc_words: Sequence[int | None] = (None, None)) -> None:
        """Set STAGED_LENGTH, the two STAGED_CRC32 and the two STAGED_COMP_CRC32 words (None: unchanged)."""
        with self._lock:
            self._banks.write_header(length, crc_words, comp_crc_words)

    def param_command(self, command: ParamCommand) -> ParamStatus:
        """OPEN_STAGING / COMMIT / ROLLBACK / SAVE; every command needs the controller DISABLED."""
        with self._lock:
            self._update()
            if self._state is not ControllerState.DISABLED:
                status = ParamStatus.NOT_DISABLED
            else:
                status = self._banks.command(command)
            self._banks.status = status
            log.info("param_command", command=command.name, status=status.name)
            return status
