"""The simulated CANopen nodes on a CAN bus: frame routing and timers, carried by the SLCAN server on a pty or by
any python-can bus (``interface="virtual"`` for in-process tests).

``CanopenDevices`` holds the nodes of one bus and routes each received frame to them (NMT and SYNC to all, SDO and
RPDOs to their node) under one lock; ``tick`` runs their timers. Frames they send collect in a ``FrameOutbox`` that
the carrier drains: ``CanopenSlcanPeer`` plugs the devices into ``sim_devices.controller.slcan_server.SlcanServer``
(its poll loop calls ``cycle_frames`` every few ms while a host has the channel open), ``CanopenBusServer`` runs
them on a python-can bus in a thread of its own.
"""

from __future__ import annotations

import threading
import time
from collections import deque
from typing import Any

import can
import structlog

from sim_devices.canopen.model import CanopenController
from sim_devices.canopen.node import SimulatedNode

log = structlog.get_logger(__name__)

Frame = tuple[int, bytes]
BUS_POLL_S = 0.002


class FrameOutbox:
    """Frames the nodes sent, in order (thread-safe); the ``network`` of their SDO servers."""

    def __init__(self) -> None:
        self._frames: deque[Frame] = deque()

    def send_message(self, can_id: int, data: bytes, remote: bool = False) -> None:
        self._frames.append((can_id, bytes(data)))

    def drain(self) -> list[Frame]:
        out = []
        while self._frames:
            out.append(self._frames.popleft())
        return out


class CanopenDevices:
    """The nodes of one bus with their controller model (see the module docstring)."""

    def __init__(self, model: CanopenController, nodes: list[SimulatedNode], outbox: FrameOutbox) -> None:
        self.model = model
        self.nodes = nodes
        self.outbox = outbox
        self.lock = threading.RLock()
        self.frames_rx = 0

    def node(self, node_id: int) -> SimulatedNode:
        return next(n for n in self.nodes if n.id == node_id)

    def power_on(self, now: float | None = None) -> None:
        """Every node boots (boot-up message, PRE-OPERATIONAL)."""
        with self.lock:
            for node in self.nodes:
                node.power_on(time.monotonic() if now is None else now)

    def handle(self, can_id: int, data: bytes, now: float) -> None:
        with self.lock:
            self.frames_rx += 1
            for node in self.nodes:
                if node.handle(can_id, data, now):
                    break

    def tick(self, now: float) -> None:
        with self.lock:
            for node in self.nodes:
                node.tick(now)

    def drain(self) -> list[Frame]:
        return self.outbox.drain()


class CanopenSlcanPeer:
    """The devices as ``SlcanServer``'s peer: frames in, frames out, timers run from its poll loop."""

    watching = True
    """Ask the SLCAN server to poll every few ms (heartbeats, TPDOs and EMCY are timed here)."""

    def __init__(self, devices: CanopenDevices) -> None:
        self.devices = devices
        self.controller = devices.model

    def reset_session(self) -> None:
        """A host opened the channel: nothing to do (a CANopen device does not see adapters come and go)."""

    def handle_frame(self, frame_id: int, data: bytes, *, extended: bool = False, remote: bool = False) -> list[Frame]:
        if not extended and not remote:
            now = time.monotonic()
            self.devices.handle(frame_id, data, now)
        return self.devices.drain()

    def cycle_frames(self, only_if_changed: bool = False) -> list[Frame]:
        self.devices.tick(time.monotonic())
        return self.devices.drain()

    def changed_cycle_frames(self) -> list[Frame]:
        return self.cycle_frames()


class CanopenBusServer:
    """The devices on a python-can bus (``bus_config`` as for ``can.Bus``), served by a thread of their own."""

    def __init__(self, devices: CanopenDevices, bus_config: dict[str, Any]) -> None:
        self.devices = devices
        self.bus_config = dict(bus_config)
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._bus: can.BusABC | None = None

    def start(self) -> CanopenBusServer:
        self._bus = can.Bus(**self.bus_config)
        self._thread = threading.Thread(target=self._run, name="canopen-bus-server", daemon=True)
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

    def _run(self) -> None:
        assert self._bus is not None
        while not self._stop.is_set():
            try:
                msg = self._bus.recv(timeout=BUS_POLL_S)
                now = time.monotonic()
                if msg is not None and not (msg.is_error_frame or msg.is_remote_frame or msg.is_extended_id):
                    self.devices.handle(msg.arbitration_id, bytes(msg.data), now)
                self.devices.tick(now)
                for frame_id, data in self.devices.drain():
                    self._bus.send(can.Message(arbitration_id=frame_id, data=data, is_extended_id=False))
            except Exception:
                log.exception("canopen_bus_server_error")
                self._stop.wait(0.01)
