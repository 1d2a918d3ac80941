"""The station's devices as the panel shows them: controller state, heartbeat age, e-stop, faults.

A thread samples what the CAN driver already knows from the heartbeats it receives; it never sends a frame
and never touches the CMM or the Modbus link (those belong to the engine), so watching cannot disturb the
run. The CMM's link state comes from the engine's own exchanges with it (see `run_view`).
"""

from __future__ import annotations

import threading
import time
from typing import Any

import structlog

log = structlog.get_logger(__name__)


def controller_status(controller: Any) -> dict[str, Any]:
    """What the driver knows now: alive, state, heartbeat age (ms), e-stop input, last fault event."""
    alive = bool(controller.controller_alive)
    age_s = controller.heartbeat_age_s
    status: dict[str, Any] = {"alive": alive, "heartbeat_age_ms": None if age_s is None else 1000.0 * age_s,
                              "heartbeat_timeout_ms": 1000.0 * controller.heartbeat_timeout_s,
                              "state": None, "estop": None, "fault": None}
    if alive:
        try:
            status["state"] = controller.state.name
            status["estop"] = bool(controller.estop_input)
            status["fault"] = controller.feedback().fault.name
        except Exception as e:  # the heartbeat may be lost between the checks
            status["alive"] = False
            status["error"] = str(e)
    event = controller.last_fault_event
    if event is not None:
        status["last_fault_event"] = {"fault": event[0].name, "state": event[1].name}
    return status


class StationMonitor:
    """Publishes the controller's status to the panel every `period_s` until `stop()`."""

    def __init__(self, live: Any, devices: Any, period_s: float = 0.25) -> None:
        self.live = live
        self.devices = devices
        self.period_s = period_s
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._loop, name="panel-station-monitor", daemon=True)
        live.update("cmm", url=devices.station.instrument_address(), kind=devices.station.instrument.kind)
        live.update("controller", parameters=devices.params.endpoint,
                    can=str(devices.station.can.bus_config().get("channel")))

    def start(self) -> StationMonitor:
        self._thread.start()
        return self

    def stop(self) -> None:
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join(self.period_s + 1.0)

    def _loop(self) -> None:
        while not self._stop.is_set():
            try:
                self.live.update("controller", **controller_status(self.devices.controller), sampled_at=time.time())
            except Exception as e:
                log.warning("panel_monitor_failed", error=str(e))
            self._stop.wait(self.period_s)
