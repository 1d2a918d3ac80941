"""The simulated laser tracker: Leica's emScon on TCP (``server``) over a transport-free state machine (``machine``)
with its own physics (``physics``: a distance meter and two encoders, refraction, MPE-shaped noise, line of sight),
its settings (``config``), fault injection (``faults``) and where its reflectors are (``targets``).

May import ``hilcal.protocols``, ``hilcal.robot``, ``sim_devices.config_base``, ``sim_devices.rotation`` and itself;
never ``drivers``.
"""

from sim_devices.tracker.config import Station, TrackerServerConfig
from sim_devices.tracker.server import TrackerServerHandle, start_tracker_server
from sim_devices.tracker.targets import default_targets, layout_reflectors, rig_reflectors

__all__ = ["Station", "TrackerServerConfig", "TrackerServerHandle", "default_targets", "layout_reflectors",
           "rig_reflectors", "start_tracker_server"]
