"""The simulated CANopen controller on its transport: the HX-6 (one node) or six LD-1 drives, their controller model,
powered up and served over SLCAN (a pty, or TCP) or on a python-can bus.

``serve_canopen`` builds the nodes of a variant around a ``CanopenController``, powers them up and starts the
carrier; ``CanopenServers.close`` stops it. The channels a host needs (the pty, the node ids, the EDS) are
``CanopenServers.channels()``.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import structlog

from hilcal.protocols.canopen import CIA402_LEG_DRIVE_EDS, HEXAPOD_CONTROLLER_EDS
from sim_devices.canopen.bus import CanopenBusServer, CanopenDevices, CanopenSlcanPeer, FrameOutbox
from sim_devices.canopen.config import CanopenSimConfig, Variant
from sim_devices.canopen.hexapod_node import HexapodNode
from sim_devices.canopen.leg_drives import LegDriveGroup
from sim_devices.canopen.model import CanopenController
from sim_devices.canopen.node import SimulatedNode
from sim_devices.canopen.nvram import Nvram
from sim_devices.controller.slcan_server import SlcanServer

log = structlog.get_logger(__name__)

EDS_OF_VARIANT = {"hexapod": HEXAPOD_CONTROLLER_EDS, "cia402": CIA402_LEG_DRIVE_EDS}


@dataclass
class CanopenServers:
    """The running simulated CANopen devices and their carrier."""

    controller: CanopenController
    devices: CanopenDevices
    variant: Variant
    node_ids: list[int]
    slcan: SlcanServer | None = None
    bus_server: CanopenBusServer | None = None
    _closed: bool = field(default=False, repr=False)

    @property
    def eds_path(self) -> Path:
        return EDS_OF_VARIANT[self.variant]

    @property
    def slcan_path(self) -> str | None:
        """Channel for ``can.Bus(interface="slcan", channel=..., sleep_after_open=0)`` (None on a python-can bus)."""
        return None if self.slcan is None else self.slcan.channel

    def channels(self) -> dict[str, Any]:
        """What a host needs to connect (JSON-serialisable)."""
        return {"variant": self.variant, "node_ids": list(self.node_ids), "eds": str(self.eds_path),
                "profile": "CiA 301 + CiA 402 device control" if self.variant == "hexapod" else "CiA 402 drives"}

    def close(self) -> None:
        """Stop the carrier (idempotent)."""
        if self._closed:
            return
        self._closed = True
        if self.slcan is not None:
            self.slcan.close()
        if self.bus_server is not None:
            self.bus_server.close()

    def __enter__(self) -> CanopenServers:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def build_devices(controller: CanopenController, variant: Variant, config: CanopenSimConfig,
                  nvram: Nvram) -> CanopenDevices:
    """The nodes of a variant around the controller model (not yet powered up)."""
    outbox = FrameOutbox()
    nodes: list[SimulatedNode]
    if variant == "hexapod":
        nodes = [HexapodNode(config.node_id, controller, outbox, nvram)]
    else:
        nodes = list(LegDriveGroup(controller, config.drive_node_ids, outbox, nvram).drives)
    return CanopenDevices(controller, nodes, outbox)


def serve_canopen(controller: CanopenController, variant: Variant = "hexapod", config: CanopenSimConfig | None = None,
                  *, nvram_path: Path | None = None, bus_config: dict[str, Any] | None = None) -> CanopenServers:
    """Power up the devices of a variant and serve them: SLCAN on a pty or TCP (the controller config's
    ``slcan_transport``), or on a python-can bus (``bus_config``, e.g. ``{"interface": "virtual", "channel": X}``).

    ``nvram_path``: where the devices keep stored dictionary values (PDO set-up, heartbeat time) across restarts."""
    cfg = config or CanopenSimConfig()
    devices = build_devices(controller, variant, cfg, Nvram(nvram_path))
    servers = CanopenServers(controller, devices, variant, cfg.node_ids(variant))
    if bus_config is not None:
        servers.bus_server = CanopenBusServer(devices, bus_config).start()
        devices.power_on()
    else:
        devices.power_on()
        devices.drain()  # the boot-up messages went out before any host had an adapter on the bus
        peer = CanopenSlcanPeer(devices)
        servers.slcan = SlcanServer(peer, transport=controller.config.slcan_transport).start()  # type: ignore[arg-type]
    log.info("canopen_servers_started", variant=variant, node_ids=servers.node_ids, channel=servers.slcan_path,
             bus=bus_config)
    return servers
