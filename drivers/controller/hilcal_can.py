"""CAN driver of the servo controller through any python-can interface (socketcan, pcan, kvaser, slcan, virtual).

Frames are those of ``hilcal/protocols/controller.dbc``. Every sent frame carries a per-ID 4-bit rolling
counter and a CRC-8/SAE-J1850 checksum; every received frame is checked, so lost (counter jump), repeated
(same counter) and corrupted (checksum) frames are counted in ``frame_stats`` and corrupted or repeated ones
are discarded. A reader thread tracks the 20 ms heartbeat (Status + 3 Feedback frames sharing a counter);
without a Status frame for ``heartbeat_timeout_s`` the controller is lost and every command except
``estop()`` raises ControllerLost until heartbeats resume. Commands are checked against the shared state
machine before sending and then acknowledged by the controller (CommandAck). An interface that keeps failing
(an adapter unplugged and back) is opened again by the reader thread.
"""

from __future__ import annotations

import contextlib
import threading
import time
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import can
import numpy as np
import structlog

from drivers.controller.base import (
    CommandRefused,
    CommandTimeout,
    ControllerError,
    ControllerFault,
    ControllerInterface,
    ControllerLost,
    EStopActive,
    Feedback,
    FrameError,
    MotionAborted,
    MotionTimeout,
    PositionMismatch,
    check_leg_limits,
    legs_not_following,
    not_following_text,
)
from drivers.controller.can_codec import ChecksumError, DecodedFrame, FrameCodec, FrameStats, UnknownFrame
from drivers.controller.slcan_bus import open_bus
from hilcal.protocols.checksums import CAN_COUNTER_MODULO
from hilcal.protocols.controller_states import (
    Command,
    ControllerState,
    FaultCode,
    RefusalReason,
    refusal_reason,
)
from hilcal.robot import Robot

log = structlog.get_logger(__name__)

UM_PER_MM = 1000
MAX_UM = (1 << 24) - 1
HEARTBEAT_PERIOD_S = 0.02
DEFAULT_HEARTBEAT_TIMEOUT_S = 5 * HEARTBEAT_PERIOD_S
REOPEN_AFTER_ERRORS = 3
"""Consecutive receive errors after which the driver opens the CAN interface again."""
REOPEN_WAIT_S = 0.5
"""Rest after a failed re-open before the next try."""
SLCAN_READ_TIMEOUT_S = 0.02
"""Serial read timeout of python-can's slcan interface unless bus_config gives one: its default (1 ms) wakes the
reader thread a thousand times a second while the line is quiet; a frame is read as soon as it arrives either way."""
FEEDBACK_NAMES = ("FeedbackL12", "FeedbackL34", "FeedbackL56")
SETPOINT_NAMES = ("SetpointL12", "SetpointL34", "SetpointL56")


@dataclass(frozen=True)
class _Snapshot:
    lengths_mm: np.ndarray
    state: ControllerState
    fault: FaultCode
    in_position: int
    setpoint_counter: int
    setpoint_valid: bool
    estop_input: bool
    received_s: float


def _state(value: int) -> ControllerState:
    try:
        return ControllerState(value)
    except ValueError:
        raise FrameError(f"unknown controller state {value}") from None


def _fault(value: int) -> FaultCode:
    try:
        return FaultCode(value)
    except ValueError:
        return FaultCode.INTERNAL


class ControllerCan(ControllerInterface):
    """The servo controller over CAN; ``bus_config`` goes to ``can.Bus(**bus_config)`` (slcan: see below and
    ``drivers.controller.slcan_bus``, which reads the adapter's port in chunks).

    Example: ``ControllerCan({"interface": "slcan", "channel": "/dev/ttyACM0", "bitrate": 500000}, robot)``. For slcan
    without a ``timeout`` the driver adds SLCAN_READ_TIMEOUT_S.
    """

    def __init__(
        self,
        bus_config: dict[str, Any],
        robot: Robot,
        *,
        heartbeat_timeout_s: float = DEFAULT_HEARTBEAT_TIMEOUT_S,
        ack_timeout_s: float = 0.5,
        position_tolerance_mm: float = 0.01,
        send_timeout_s: float = 0.1,
    ) -> None:
        self.robot = robot
        self.heartbeat_timeout_s = heartbeat_timeout_s
        self.ack_timeout_s = ack_timeout_s
        self.position_tolerance_mm = position_tolerance_mm
        self._send_timeout_s = send_timeout_s
        self._codec = FrameCodec()
        self.frame_stats = FrameStats()
        self._cond = threading.Condition()
        self._send_lock = threading.Lock()
        self._command_lock = threading.Lock()
        self._tx_counters: dict[str, int] = {}
        self._rx_last: dict[int, tuple[int, float]] = {}
        self._acks: dict[tuple[int, int], tuple[RefusalReason, ControllerState, float]] = {}
        self._cycle: tuple[int, dict[str, dict[str, int]]] | None = None
        self._orphan_cycle: int | None = None
        self._snapshot: _Snapshot | None = None
        self._last_status_s: float | None = None
        self._state_value: ControllerState | None = None
        self._estop_input = False
        self.last_fault_event: tuple[FaultCode, ControllerState] | None = None
        self._was_alive = False
        self._stop = threading.Event()
        self._bus_config = dict(bus_config)
        if self._bus_config.get("interface") == "slcan":
            self._bus_config.setdefault("timeout", SLCAN_READ_TIMEOUT_S)
        try:
            self._bus = open_bus(self._bus_config)
        except (can.CanError, OSError, ValueError) as err:
            raise ControllerError(f"cannot open the CAN interface {bus_config!r}: {err}") from err
        self._closed = False
        self._reader = threading.Thread(target=self._read_loop, name="controller-can-reader", daemon=True)
        self._reader.start()
        log.info("controller_can_opened", bus=str(bus_config.get("interface")), channel=bus_config.get("channel"))

    # ------------------------------------------------------------------ receive side

    def _read_loop(self) -> None:
        errors = 0
        while not self._stop.is_set():
            try:
                msg = self._bus.recv(timeout=0.02)
            except (can.CanError, OSError, ValueError) as err:
                self.frame_stats.transport_errors += 1
                errors += 1
                log.warning("can_receive_error", error=str(err), consecutive=errors)
                self._track_liveness()
                if errors >= REOPEN_AFTER_ERRORS:
                    errors = 0 if self._reopen() else errors
                self._stop.wait(0.01)
                continue
            errors = 0
            if msg is not None:
                self._on_message(msg)
            self._track_liveness()

    def _reopen(self) -> bool:
        """Open the CAN interface again (an adapter unplugged and back); one try, then REOPEN_WAIT_S of rest.

        While the interface is down no heartbeat arrives, so the controller counts as lost and nothing is sent;
        how long a run waits for it is the procedure's decision (its grace period), not the driver's.
        """
        with self._send_lock:
            with contextlib.suppress(can.CanError, OSError, ValueError):
                self._bus.shutdown()
            try:
                self._bus = open_bus(self._bus_config)
            except (can.CanError, OSError, ValueError) as err:
                log.warning("can_reopen_failed", error=str(err))
                self._stop.wait(REOPEN_WAIT_S)
                return False
        self.frame_stats.reopens += 1
        log.warning("can_reopened", reopens=self.frame_stats.reopens)
        return True

    def _track_liveness(self) -> None:
        alive = self.controller_alive
        if alive != self._was_alive:
            self._was_alive = alive
            (log.info if alive else log.warning)("controller_heartbeat", alive=alive)
            with self._cond:
                self._cond.notify_all()

    def _on_message(self, msg: can.Message) -> None:
        if msg.is_error_frame or msg.is_remote_frame or msg.is_extended_id:
            return
        self.frame_stats.rx_frames += 1
        try:
            frame = self._codec.decode(msg.arbitration_id, bytes(msg.data))
        except UnknownFrame:
            self.frame_stats.unknown_ids += 1
            return
        except ChecksumError as err:
            self.frame_stats.checksum_errors += 1
            log.warning("can_frame_rejected", error=str(err))
            return
        except FrameError as err:
            self.frame_stats.invalid_frames += 1
            log.warning("can_frame_rejected", error=str(err))
            return
        if not self._codec.sent_by_controller(msg.arbitration_id):
            return
        now = time.monotonic()
        if not self._check_counter(msg.arbitration_id, frame.counter, now):
            return
        try:
            with self._cond:
                self._apply(frame, now)
                self._cond.notify_all()
        except FrameError as err:
            self.frame_stats.invalid_frames += 1
            log.warning("can_frame_rejected", error=str(err))

    def _check_counter(self, frame_id: int, counter: int, now: float) -> bool:
        """False for a repeated frame; counts frames lost in a counter jump; resyncs after silence."""
        previous = self._rx_last.get(frame_id)
        if previous is not None and now - previous[1] <= self.heartbeat_timeout_s:
            delta = (counter - previous[0]) % CAN_COUNTER_MODULO
            if delta == 0:
                self.frame_stats.repeated += 1
                return False
            self.frame_stats.lost += delta - 1
        self._rx_last[frame_id] = (counter, now)
        return True

    def _apply(self, frame: DecodedFrame, now: float) -> None:
        s = frame.signals
        if frame.name == "Status":
            if self._cycle is not None:
                self.frame_stats.incomplete_cycles += 1
            self._cycle = (frame.counter, {"Status": s})
            self._last_status_s = now
            self._state_value = _state(s["State"])
            self._estop_input = bool(s["EstopInput"])
        elif frame.name in FEEDBACK_NAMES:
            if self._cycle is None or self._cycle[0] != frame.counter:
                if frame.counter != self._orphan_cycle:
                    self._orphan_cycle = frame.counter
                    self.frame_stats.incomplete_cycles += 1
                self._cycle = None
                return
            self._cycle[1][frame.name] = s
            if len(self._cycle[1]) == 1 + len(FEEDBACK_NAMES):
                self._publish(self._cycle[1], now)
                self._cycle = None
        elif frame.name == "CommandAck":
            state = _state(s["State"])
            try:
                reason = RefusalReason(s["Reason"])
            except ValueError:
                reason = RefusalReason.UNKNOWN_COMMAND
            self._acks[(s["CommandCode"], s["RequestCounter"])] = (reason, state, now)
            self._state_value = state
        elif frame.name == "FaultEvent":
            fault, state = _fault(s["FaultCode"]), _state(s["State"])
            self.last_fault_event = (fault, state)
            self._state_value = state
            log.warning("controller_fault_event", fault=fault.name, state=state.name)

    def _publish(self, parts: dict[str, dict[str, int]], now: float) -> None:
        status = parts["Status"]
        um = [parts[name][f"Leg{leg}Length"] for name in FEEDBACK_NAMES for leg in (int(name[-2]), int(name[-1]))]
        self._snapshot = _Snapshot(
            lengths_mm=np.asarray(um, dtype=float) / UM_PER_MM,
            state=_state(status["State"]),
            fault=_fault(status["FaultCode"]),
            in_position=status["InPosition"],
            setpoint_counter=status["SetpointCounter"],
            setpoint_valid=bool(status["SetpointValid"]),
            estop_input=bool(status["EstopInput"]),
            received_s=now,
        )

    # ------------------------------------------------------------------ liveness and state

    @property
    def heartbeat_age_s(self) -> float | None:
        """Seconds since the last Status frame (None: none received yet)."""
        last = self._last_status_s
        return None if last is None else time.monotonic() - last

    @property
    def controller_alive(self) -> bool:
        """True while Status frames arrive within ``heartbeat_timeout_s``."""
        last = self._last_status_s
        return last is not None and time.monotonic() - last <= self.heartbeat_timeout_s

    def _require_alive(self) -> None:
        if not self.controller_alive:
            last = self._last_status_s
            age = "never received" if last is None else f"last {time.monotonic() - last:.3f} s ago"
            raise ControllerLost(
                f"controller lost: no heartbeat within {self.heartbeat_timeout_s:.3f} s ({age}); "
                "commands are refused until heartbeats resume"
            )

    def wait_for_heartbeat(self, timeout_s: float = 1.0) -> Feedback:
        """Block until a complete heartbeat (Status + Feedback) arrives; ControllerLost after timeout_s."""
        deadline = time.monotonic() + timeout_s
        with self._cond:
            while not (self.controller_alive and self._snapshot is not None
                       and time.monotonic() - self._snapshot.received_s <= self.heartbeat_timeout_s):
                remaining = deadline - time.monotonic()
                if remaining <= 0:
                    self._require_alive()
                    raise ControllerLost(f"no complete heartbeat (status + feedback) within {timeout_s} s")
                self._cond.wait(min(remaining, 0.02))
        return self.feedback()

    @property
    def state(self) -> ControllerState:
        self._require_alive()
        if self._state_value is None:
            raise ControllerLost("no controller state received yet")
        return self._state_value

    @property
    def estop_input(self) -> bool:
        """The hardware e-stop input as the latest Status reports it (True: pressed)."""
        self._require_alive()
        return self._estop_input

    def feedback(self) -> Feedback:
        self._require_alive()
        snap = self._snapshot
        if snap is None or time.monotonic() - snap.received_s > self.heartbeat_timeout_s:
            raise ControllerLost("no complete feedback (status + 3 feedback frames) within the heartbeat timeout")
        return Feedback(snap.lengths_mm.copy(), snap.state, snap.fault)

    # ------------------------------------------------------------------ send side

    def _next_counter(self, key: str) -> int:
        counter = self._tx_counters.get(key, 0)
        self._tx_counters[key] = (counter + 1) % CAN_COUNTER_MODULO
        return counter

    def _send(self, name: str, signals: dict[str, int], counter: int) -> None:
        self._send_frames([(name, signals)], counter)

    def _send_frames(self, frames: list[tuple[str, dict[str, int]]], counter: int) -> None:
        """Send frames in order; an interface with ``send_batch`` (``ChunkedSlcanBus``) gets them in one write."""
        msgs = [self._codec.encode(name, signals, counter) for name, signals in frames]
        send_batch = getattr(self._bus, "send_batch", None)
        try:
            with self._send_lock:
                if send_batch is not None and len(msgs) > 1:
                    send_batch(msgs, timeout=self._send_timeout_s)
                else:
                    for msg in msgs:
                        self._bus.send(msg, timeout=self._send_timeout_s)
        except can.CanError as err:
            raise ControllerLost(f"cannot send {', '.join(name for name, _ in frames)}: {err}") from err
        self.frame_stats.tx_frames += len(msgs)

    def _refuse_locally(self, command: Command) -> None:
        state = self.state
        reason = refusal_reason(state, command)
        if reason is RefusalReason.ACCEPTED and command is Command.FAULT_RESET and self._estop_input:
            reason = RefusalReason.ESTOP_NOT_RELEASED
        if reason is not RefusalReason.ACCEPTED:
            raise CommandRefused(
                f"{command.name} refused in state {state.name}: {reason.name} (not sent)", reason, state, "driver"
            )

    def _wait_ack(self, command: Command, counter: int, sent_s: float) -> tuple[RefusalReason, ControllerState, float]:
        """The acknowledgement of the command sent at sent_s with this counter.

        An acknowledgement received before sent_s answers an earlier command with the same 4-bit counter whose
        wait timed out (it came late): it is discarded, so it cannot pass for this command's.
        """
        deadline = time.monotonic() + self.ack_timeout_s
        key = (int(command), counter)
        with self._cond:
            while key not in self._acks or self._acks[key][2] < sent_s:
                if key in self._acks:
                    log.warning("can_stale_ack_discarded", command=command.name, counter=counter)
                    del self._acks[key]
                    continue
                remaining = deadline - time.monotonic()
                if remaining <= 0:
                    raise CommandTimeout(
                        f"no acknowledgement of {command.name} (counter {counter}) within {self.ack_timeout_s} s: "
                        "the controller may or may not have executed it; read the state"
                    )
                self._cond.wait(remaining)
            return self._acks.pop(key)

    def _command(self, command: Command) -> None:
        with self._command_lock:
            self._refuse_locally(command)
            counter = self._next_counter("Command")
            sent_s = time.monotonic()
            self._send("Command", {"CommandCode": int(command)}, counter)
            reason, state, _ = self._wait_ack(command, counter, sent_s)
        if reason is not RefusalReason.ACCEPTED:
            raise CommandRefused(f"controller refused {command.name} in state {state.name}: {reason.name}",
                                 reason, state, "controller")
        log.info("controller_command", command=command.name, state=state.name)

    def enable(self) -> None:
        self._command(Command.ENABLE)

    def disable(self) -> None:
        self._command(Command.DISABLE)

    def stop(self) -> None:
        self._command(Command.STOP)

    def fault_reset(self) -> None:
        self._command(Command.FAULT_RESET)

    def estop(self) -> None:
        """Send EstopRequest every heartbeat period until ESTOP is reported (sent even if the link looks lost)."""
        deadline = time.monotonic() + self.ack_timeout_s
        log.warning("controller_estop_requested")
        while True:
            self._send("EstopRequest", {"EstopActive": 1}, self._next_counter("EstopRequest"))
            with self._cond:
                self._cond.wait_for(lambda: self._state_value is ControllerState.ESTOP, HEARTBEAT_PERIOD_S)
                if self._state_value is ControllerState.ESTOP and self.controller_alive:
                    return
            if time.monotonic() >= deadline:
                self._require_alive()
                raise CommandTimeout(f"e-stop sent but ESTOP not reported within {self.ack_timeout_s} s")

    def move_legs(self, lengths_mm: Sequence[float] | np.ndarray, timeout_s: float) -> np.ndarray:
        """Move to controller lengths (mm) and wait for IN_POSITION; the measured lengths (mm).

        The setpoint is checked against ``robot.leg_limits`` before anything is sent (LimitViolation). On a
        timeout the driver sends STOP and raises MotionTimeout.
        """
        target = check_leg_limits(self.robot, lengths_mm)
        um = [round(v * UM_PER_MM) for v in target]
        if any(not 0 <= v <= MAX_UM for v in um):
            raise FrameError(f"lengths {target.tolist()} mm do not fit the 24-bit um encoding")
        with self._command_lock:
            self._refuse_locally(Command.SETPOINT)
            before = None if self._snapshot is None else self._snapshot.lengths_mm.copy()
            counter = self._next_counter("Setpoint")
            sent_s = time.monotonic()
            self._send_frames([(name, {f"Leg{2 * k + 1}Setpoint": um[2 * k], f"Leg{2 * k + 2}Setpoint": um[2 * k + 1]})
                               for k, name in enumerate(SETPOINT_NAMES)], counter)
            reason, state, acked_s = self._wait_ack(Command.SETPOINT, counter, sent_s)
        if reason is not RefusalReason.ACCEPTED:
            raise CommandRefused(f"controller refused the setpoint in state {state.name}: {reason.name}",
                                 reason, state, "controller")
        snap = self._wait_in_position(counter, acked_s, time.monotonic() + timeout_s, timeout_s, before, target)
        error = np.abs(snap.lengths_mm - target)
        if float(error.max()) > self.position_tolerance_mm:
            raise PositionMismatch(
                f"IN_POSITION reported but feedback differs from the setpoint by up to {error.max():.4f} mm "
                f"(tolerance {self.position_tolerance_mm} mm)"
            )
        return snap.lengths_mm.copy()

    def _wait_in_position(self, counter: int, acked_s: float, deadline: float, timeout_s: float,
                          before: np.ndarray | None, target: np.ndarray) -> _Snapshot:
        """Wait for IN_POSITION of this setpoint. A fault or a timeout names the legs whose reading did not follow
        (``legs_not_following``, over the readings before the move and every snapshot seen during it)."""
        lowest = highest = before

        def stuck(snap: _Snapshot) -> tuple[list[int], str]:
            if before is None or lowest is None or highest is None:
                return [], ""
            legs = legs_not_following(before, lowest, highest, target)
            return legs, (f": {not_following_text(legs, snap.lengths_mm, target, self.robot.leg_limits)}"
                          if legs else "")

        with self._cond:
            while True:
                self._require_alive()
                snap = self._snapshot
                if snap is not None and snap.received_s > acked_s:
                    if lowest is not None and highest is not None:
                        lowest, highest = np.minimum(lowest, snap.lengths_mm), np.maximum(highest, snap.lengths_mm)
                    if snap.state is ControllerState.ESTOP:
                        raise EStopActive(f"e-stop during the move ({snap.fault.name})", snap.state, snap.fault)
                    if snap.state is ControllerState.FAULT:
                        legs, text = stuck(snap)
                        raise ControllerFault(f"controller fault {snap.fault.name} during the move{text}",
                                              snap.state, snap.fault, legs)
                    ours = snap.setpoint_valid and snap.setpoint_counter == counter
                    if snap.state is ControllerState.IN_POSITION and ours:
                        return snap
                    if snap.state in (ControllerState.ENABLED, ControllerState.DISABLED) or not ours:
                        raise MotionAborted(f"move ended in state {snap.state.name} without IN_POSITION")
                remaining = deadline - time.monotonic()
                if remaining <= 0:
                    break
                self._cond.wait(min(remaining, HEARTBEAT_PERIOD_S))
        try:
            self.stop()
        except Exception as err:
            log.warning("stop_after_timeout_failed", error=str(err))
        text = stuck(snap)[1] if snap is not None else ""
        raise MotionTimeout(f"legs not in position within {timeout_s} s; STOP sent{text}")

    def close(self) -> None:
        """Stop the reader thread and shut the bus down (the controller state is left as it is)."""
        if self._closed:
            return
        self._closed = True
        self._stop.set()
        self._reader.join(timeout=2.0)
        try:
            self._bus.shutdown()
        except (can.CanError, OSError) as err:
            log.warning("can_shutdown_error", error=str(err))
        log.info("controller_can_closed")
