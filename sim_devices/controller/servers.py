"""The simulated controller on its transports: SLCAN (pty or TCP), Modbus TCP and optionally Modbus RTU.

The composition the launcher uses: one transport-free ``SimulatedController`` adapted by one server per
protocol. ``serve_controller`` starts them; ``ControllerServers.close`` stops them.
"""

from __future__ import annotations

from dataclasses import dataclass

import structlog

from hilcal.robot import Robot
from sim_devices.controller.can_peer import ControllerCanPeer
from sim_devices.controller.modbus_server import ModbusRtuServer, ModbusTcpServer
from sim_devices.controller.slcan_server import SlcanServer
from sim_devices.controller.state_machine import ControllerSimConfig, SimulatedController
from sim_devices.rig.rig import SimulatedRig

log = structlog.get_logger(__name__)


@dataclass
class ControllerServers:
    """The running simulated controller with its SLCAN and Modbus TCP servers."""

    controller: SimulatedController
    slcan: SlcanServer
    modbus: ModbusTcpServer
    modbus_rtu: ModbusRtuServer | None = None

    @property
    def slcan_path(self) -> str:
        """Channel for ``can.Bus(interface="slcan", channel=..., sleep_after_open=0)``."""
        return self.slcan.channel

    @property
    def modbus_port(self) -> int:
        return self.modbus.port

    @property
    def modbus_rtu_path(self) -> str | None:
        """pty of the Modbus RTU server (``modbus_rtu=True`` in the config), else None."""
        return self.modbus_rtu.path if self.modbus_rtu is not None else None

    def close(self) -> None:
        """Stop every server (idempotent)."""
        self.slcan.close()
        self.modbus.close()
        if self.modbus_rtu is not None:
            self.modbus_rtu.close()

    def __enter__(self) -> ControllerServers:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def serve_controller(controller: SimulatedController) -> ControllerServers:
    """Serve a controller model on SLCAN (pty or TCP), Modbus TCP (127.0.0.1) and optionally Modbus RTU (pty)."""
    cfg = controller.config
    slcan = SlcanServer(ControllerCanPeer(controller), transport=cfg.slcan_transport).start()
    servers = ControllerServers(controller, slcan, ModbusTcpServer(controller, port=cfg.modbus_port))
    try:
        servers.modbus.start()
        if cfg.modbus_rtu:
            servers.modbus_rtu = ModbusRtuServer(controller, faults=servers.modbus.faults).start()
    except BaseException:
        servers.close()
        raise
    log.info("controller_servers_started", slcan=slcan.channel, modbus_port=servers.modbus_port,
             modbus_rtu=servers.modbus_rtu_path)
    return servers


def start_controller_servers(
    robot: Robot, rig: SimulatedRig, config: ControllerSimConfig | None = None
) -> ControllerServers:
    """Start a simulated controller and serve it (see `serve_controller`); ``close()`` stops every server.

    Fault injection starts as the config says.
    """
    return serve_controller(SimulatedController(robot, rig, config or ControllerSimConfig()))
