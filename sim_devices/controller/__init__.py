"""The simulated servo controller: a transport-free state machine (``state_machine``) and one adapter per
protocol: CAN (``can_peer`` with ``can_faults``, served over SLCAN by ``slcan_server`` and ``slcan_protocol`` or
on any python-can bus by ``can_bus_server``; ``link_gaps`` silences it for a while) and Modbus (``modbus_frames``,
``modbus_faults``, ``modbus_protocol``, served by ``modbus_server``). ``servers`` starts the model on all its
transports.

May import ``hilcal.protocols``, ``hilcal.robot``, ``sim_devices.rig``, ``sim_devices.config_base`` and itself;
never ``drivers``. A new transport is a new server module here that adapts ``SimulatedController``.
"""

from sim_devices.controller.servers import ControllerServers, serve_controller, start_controller_servers
from sim_devices.controller.state_machine import ControllerSimConfig, SimulatedController

__all__ = [
    "ControllerServers",
    "ControllerSimConfig",
    "SimulatedController",
    "serve_controller",
    "start_controller_servers",
]
