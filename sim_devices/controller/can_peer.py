"""The simulated controller's CAN protocol: DBC frame codec, rolling-counter check and the controller peer.

``ControllerCanPeer`` speaks the frames of ``hilcal/protocols/controller.dbc`` (counter and checksum checked on
every received frame, set on every sent one): frames in -> ``SimulatedController`` calls -> acknowledgement
frames, plus the heartbeat frames. Transport-free: ``slcan_server.py`` and ``can_bus_server.py`` carry its frames.
Independent of ``drivers``: only the shared protocol data is imported.
"""

from __future__ import annotations

import threading
import time
from collections import Counter
from dataclasses import dataclass, field

import cantools
import structlog

from hilcal.protocols import controller_dbc_text
from hilcal.protocols.checksums import (
    CAN_CHECKSUM_BYTE,
    CAN_COUNTER_BYTE,
    CAN_COUNTER_MODULO,
    CAN_PAYLOAD_BYTES,
    can_frame_checksum,
)
from hilcal.protocols.controller_states import Command, ControllerState, RefusalReason
from sim_devices.controller.state_machine import SimulatedController

log = structlog.get_logger(__name__)


Frame = tuple[int, bytes]
UM_PER_MM = 1000
MAX_UM = (1 << 24) - 1
COUNTER_RESYNC_S = 1.0


class CanFrameError(ValueError):
    """A received frame that is not a valid controller frame."""


class UnknownFrameId(CanFrameError):
    pass


class BadFrameLength(CanFrameError):
    pass


class BadChecksum(CanFrameError):
    pass


class CanCodec:
    """Encode/decode controller frames with the shared DBC; counter and checksum are handled here."""

    def __init__(self) -> None:
        self.db = cantools.database.load_string(controller_dbc_text(), "dbc")
        self._by_id = {m.frame_id: m for m in self.db.messages}
        self._by_name = {m.name: m for m in self.db.messages}
        for m in self.db.messages:
            signals = {s.name: s for s in m.signals}
            counter, checksum = signals.get("Counter"), signals.get("Checksum")
            if (
                m.length != CAN_PAYLOAD_BYTES
                or counter is None
                or (counter.start, counter.length) != (CAN_COUNTER_BYTE * 8, 4)
                or checksum is None
                or (checksum.start, checksum.length) != (CAN_CHECKSUM_BYTE * 8, 8)
            ):
                raise ValueError(f"DBC message {m.name} does not follow the counter/checksum layout")

    def frame_id(self, name: str) -> int:
        return self._by_name[name].frame_id

    def senders(self, frame_id: int) -> list[str]:
        return list(self._by_id[frame_id].senders)

    def encode(self, name: str, signals: dict[str, int], counter: int) -> Frame:
        """Raw (unscaled) signal values -> (frame ID, 8 bytes) with counter and checksum set."""
        message = self._by_name[name]
        data = bytearray(message.encode({**signals, "Counter": counter % CAN_COUNTER_MODULO, "Checksum": 0},
                                        scaling=False))
        data[CAN_CHECKSUM_BYTE] = can_frame_checksum(message.frame_id, data)
        return message.frame_id, bytes(data)

    def decode(self, frame_id: int, data: bytes) -> tuple[str, dict[str, int]]:
        """(message name, raw signal values); raises a CanFrameError subclass for anything invalid."""
        message = self._by_id.get(frame_id)
        if message is None:
            raise UnknownFrameId(f"unknown frame ID 0x{frame_id:X}")
        if len(data) != message.length:
            raise BadFrameLength(f"{message.name}: {len(data)} data bytes, expected {message.length}")
        if data[CAN_CHECKSUM_BYTE] != can_frame_checksum(frame_id, data):
            raise BadChecksum(f"{message.name}: checksum mismatch")
        decoded = message.decode(bytes(data), decode_choices=False, scaling=False)
        return message.name, {k: int(v) for k, v in decoded.items()}


class CounterTracker:
    """Per-ID rolling-counter check: delta 0 = repeated (discard), delta n > 1 = n - 1 frames lost."""

    def __init__(self) -> None:
        self._last: dict[int, tuple[int, float]] = {}

    def reset(self) -> None:
        self._last.clear()

    def check(self, frame_id: int, counter: int, now: float) -> tuple[bool, int]:
        """(is_repeat, frames_lost) and remember this counter unless it is a repeat."""
        previous = self._last.get(frame_id)
        if previous is None or now - previous[1] > COUNTER_RESYNC_S:
            self._last[frame_id] = (counter, now)
            return False, 0
        delta = (counter - previous[0]) % CAN_COUNTER_MODULO
        if delta == 0:
            return True, 0
        self._last[frame_id] = (counter, now)
        return False, delta - 1


@dataclass
class PeerStats:
    """What the controller noticed on its CAN input."""

    rx_frames: int = 0
    rx_checksum_errors: int = 0
    rx_bad_length: int = 0
    rx_unknown_id: int = 0
    rx_ignored: int = 0
    rx_repeated: int = 0
    rx_lost: int = 0
    rx_by_name: Counter[str] = field(default_factory=Counter)
    tx_frames: int = 0


_SETPOINT_PAIRS = {"SetpointL12": 0, "SetpointL34": 1, "SetpointL56": 2}


STATE_POLL_S = 0.002
"""While a move is under way the server checks the state this often and sends Status at once on a change."""
WATCH_AFTER_SETPOINT_S = 0.5


class ControllerCanPeer:
    """The controller's CAN protocol: frames in -> model calls -> acknowledgement frames; heartbeat frames."""

    def __init__(self, controller: SimulatedController) -> None:
        self.controller = controller
        self.codec = CanCodec()
        self.stats = PeerStats()
        self._lock = threading.Lock()
        self._rx_counters = CounterTracker()
        self._tx_counters: Counter[str] = Counter()
        self._cycle = 0
        self._pending: dict[int, tuple[int, tuple[int, int]]] = {}
        self._fault_events_seen = controller.snapshot().fault_events
        self._state_sent: ControllerState | None = None
        self._watch_until = 0.0

    def changed_cycle_frames(self) -> list[Frame]:
        """``cycle_frames()`` when the controller's state differs from the last status sent (or a setpoint came
        since), else none; one snapshot of the controller for the check and the frames."""
        return self.cycle_frames(only_if_changed=True)

    @property
    def watching(self) -> bool:
        """A move is (or may be) under way: the last status said MOVING, or a setpoint arrived recently and no
        status has been sent since (once one says IN_POSITION there is nothing left to watch for)."""
        return self._state_sent == ControllerState.MOVING or (
            self._state_sent is None and time.monotonic() < self._watch_until)

    def reset_session(self) -> None:
        """A new host session (SLCAN channel opened): forget received counters and partial setpoints."""
        with self._lock:
            self._rx_counters.reset()
            self._pending.clear()

    def _next_tx(self, name: str, signals: dict[str, int]) -> Frame:
        counter = self._tx_counters[name]
        self._tx_counters[name] = (counter + 1) % CAN_COUNTER_MODULO
        self.stats.tx_frames += 1
        return self.codec.encode(name, signals, counter)

    def _ack(self, command: int, reason: RefusalReason, request_counter: int,
             state: ControllerState | None = None) -> Frame:
        """CommandAck with the state the command left the controller in (docs/protocols.md: "State after"): given
        when the command defines it, else the controller's state now."""
        state = self.controller.snapshot().state if state is None else state
        signals = {"CommandCode": command, "Reason": int(reason), "State": int(state),
                   "RequestCounter": request_counter}
        return self._next_tx("CommandAck", signals)

    def handle_frame(self, frame_id: int, data: bytes, *, extended: bool = False, remote: bool = False) -> list[Frame]:
        """Process one received frame; returns the frames to send in answer (possibly none)."""
        with self._lock:
            self.stats.rx_frames += 1
            if extended or remote:
                self.stats.rx_ignored += 1
                return []
            try:
                name, signals = self.codec.decode(frame_id, data)
            except UnknownFrameId:
                self.stats.rx_unknown_id += 1
                return []
            except BadFrameLength:
                self.stats.rx_bad_length += 1
                return []
            except BadChecksum:
                self.stats.rx_checksum_errors += 1
                log.warning("can_rx_checksum_error", frame_id=hex(frame_id))
                return []
            if "HOST" not in self.codec.senders(frame_id):
                self.stats.rx_ignored += 1
                return []
            counter = signals["Counter"]
            repeated, lost = self._rx_counters.check(frame_id, counter, time.monotonic())
            self.stats.rx_lost += lost
            if repeated:
                self.stats.rx_repeated += 1
                return []
            self.stats.rx_by_name[name] += 1
            return self._dispatch(name, signals, counter)

    def _dispatch(self, name: str, signals: dict[str, int], counter: int) -> list[Frame]:
        if name == "EstopRequest":
            if signals["EstopActive"]:
                self.controller.press_estop(source="request")
            return []
        if name == "Command":
            code = signals["CommandCode"]
            try:
                command = Command(code)
            except ValueError:
                return [self._ack(code, RefusalReason.UNKNOWN_COMMAND, counter)]
            return [self._ack(code, self.controller.command(command), counter)]
        index = _SETPOINT_PAIRS[name]
        first, second = (v for k, v in signals.items() if k.endswith("Setpoint"))
        self._pending[index] = (counter, (first, second))
        if index < 2:
            return []
        parts = [self._pending.get(i) for i in range(3)]
        self._pending.clear()
        if any(p is None or p[0] != counter for p in parts):
            return [self._ack(Command.SETPOINT, RefusalReason.SETPOINT_INCOMPLETE, counter)]
        lengths_mm = [um / UM_PER_MM for p in parts if p is not None for um in p[1]]
        reason = self.controller.set_setpoint(lengths_mm, tag=counter)
        self._watch_until = time.monotonic() + WATCH_AFTER_SETPOINT_S
        self._state_sent = None
        # an accepted setpoint starts a move: MOVING, even if a fast servo has arrived by the time the ack is made
        after = ControllerState.MOVING if reason is RefusalReason.ACCEPTED else None
        return [self._ack(Command.SETPOINT, reason, counter, after)]

    def cycle_frames(self, only_if_changed: bool = False) -> list[Frame]:
        """One heartbeat: [FaultEvent if a fault happened,] Status, FeedbackL12, FeedbackL34, FeedbackL56.

        only_if_changed: none unless the state differs from the last status sent.
        """
        with self._lock:
            snap = self.controller.snapshot()
            if only_if_changed and snap.state == self._state_sent:
                return []
            self._state_sent = snap.state
            frames = []
            if snap.fault_events != self._fault_events_seen:
                self._fault_events_seen = snap.fault_events
                frames.append(self._next_tx("FaultEvent", {"FaultCode": int(snap.fault), "State": int(snap.state),
                                                           "EstopInput": int(snap.estop_input)}))
            cycle = self._cycle
            self._cycle = (cycle + 1) % CAN_COUNTER_MODULO
            in_position = sum(1 << i for i, flag in enumerate(snap.in_position) if flag)
            status = {
                "State": int(snap.state),
                "EstopInput": int(snap.estop_input),
                "FaultCode": int(snap.fault),
                "InPosition": in_position,
                "SetpointCounter": snap.setpoint_tag % CAN_COUNTER_MODULO,
                "SetpointValid": int(snap.setpoint_valid),
            }
            frames.append(self.codec.encode("Status", status, cycle))
            um = [min(MAX_UM, max(0, round(v * UM_PER_MM))) for v in snap.lengths_mm]
            for k, name in enumerate(("FeedbackL12", "FeedbackL34", "FeedbackL56")):
                a, b = 2 * k + 1, 2 * k + 2
                frames.append(self.codec.encode(name, {f"Leg{a}Length": um[a - 1], f"Leg{b}Length": um[b - 1]}, cycle))
            self.stats.tx_frames += 4
            return frames
