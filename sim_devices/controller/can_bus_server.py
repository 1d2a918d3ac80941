"""Serve the simulated controller's CAN peer on any python-can bus (``interface="virtual"`` for fast tests)."""

from __future__ import annotations

import threading
import time
from typing import Any

import can
import structlog

from sim_devices.controller.can_faults import CanFaultInjector, FrameOutbox
from sim_devices.controller.can_peer import STATE_POLL_S, ControllerCanPeer, Frame

log = structlog.get_logger(__name__)


class CanBusServer:
    """Serve the controller peer on any python-can bus (``interface="virtual"`` for fast in-process tests)."""

    def __init__(
        self,
        peer: ControllerCanPeer,
        bus_config: dict[str, Any],
        faults: CanFaultInjector | None = None,
        *,
        heartbeat_period_s: float | None = None,
    ) -> None:
        self.peer = peer
        self.bus_config = dict(bus_config)
        self.faults = faults or CanFaultInjector(peer.controller.config.can_faults)
        self.heartbeat_period_s = heartbeat_period_s or peer.controller.config.heartbeat_period_s
        self._outbox = FrameOutbox(self.faults)
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._bus: can.BusABC | None = None

    def start(self) -> CanBusServer:
        self._bus = can.Bus(**self.bus_config)
        self._thread = threading.Thread(target=self._run, name="can-bus-server", daemon=True)
        self._thread.start()
        return self

    def close(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=5.0)
            self._thread = None
        if self._bus is not None:
            self._bus.shutdown()
            self._bus = None

    def __enter__(self) -> CanBusServer:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def _send(self, frames: list[Frame]) -> None:
        for frame_id, data in frames:
            self._bus.send(can.Message(arbitration_id=frame_id, data=data, is_extended_id=False))

    def _run(self) -> None:
        next_heartbeat = time.monotonic()
        while not self._stop.is_set():
            try:
                next_heartbeat = self._step(next_heartbeat)
            except Exception:
                log.exception("can_bus_server_error")
                self._stop.wait(0.01)

    def _step(self, next_heartbeat: float) -> float:
        now = time.monotonic()
        due = self._outbox.next_due()
        wait = min(next_heartbeat, due if due is not None else next_heartbeat) - now
        if self.peer.watching:
            wait = min(wait, STATE_POLL_S)
        msg = self._bus.recv(timeout=max(0.0, min(wait, 0.05)))
        now = time.monotonic()
        if msg is not None and not msg.is_error_frame:
            for _, data in self.faults.apply("rx", msg.arbitration_id, bytes(msg.data)):
                responses = self.peer.handle_frame(msg.arbitration_id, data, extended=msg.is_extended_id,
                                                   remote=msg.is_remote_frame)
                self._send(self._outbox.schedule(responses, now))
        if now >= next_heartbeat:
            if self.faults.heartbeat:
                self._send(self._outbox.schedule(self.peer.cycle_frames(), now))
            next_heartbeat += self.heartbeat_period_s
            if next_heartbeat < now:
                next_heartbeat = now + self.heartbeat_period_s
        elif self.faults.heartbeat:
            self._send(self._outbox.schedule(self.peer.changed_cycle_frames(), now))
        self._send(self._outbox.due(now))
        return next_heartbeat
